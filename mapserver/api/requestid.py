"""Request ids: every response carries ``X-Request-ID``; 5xx bodies, job records and the server log name it.

:class:`RequestIdMiddleware` (pure ASGI, so streamed bodies pass through untouched) gives each request
an id — the client's ``X-Request-ID`` when it is 1 to 64 characters of ``A-Z a-z 0-9 . _ -``, else 16
random hex digits —, keeps it in ``request.state.request_id`` and in a context variable for the log,
adds the header to the response, and answers an exception no handler took with a 500 that names only
the id (the traceback goes to the server log with the same id).
"""

from __future__ import annotations

import json
import logging
import re
import secrets
from contextvars import ContextVar

from starlette.types import ASGIApp, Message, Receive, Scope, Send

logger = logging.getLogger(__name__)

REQUEST_ID_HEADER = "X-Request-ID"
_HEADER_KEY = REQUEST_ID_HEADER.lower().encode("latin-1")
_SAFE = re.compile(r"[A-Za-z0-9._-]{1,64}")
_current: ContextVar[str | None] = ContextVar("mapserver_request_id", default=None)


def new_request_id() -> str:
    """Return a fresh request id (16 hex digits)."""
    return secrets.token_hex(8)


def current_request_id() -> str | None:
    """Return the id of the request being handled in this context (None outside a request)."""
    return _current.get()


def internal_error_detail(reference: str) -> str:
    """Return the ``detail`` of a 5xx answer or a job's internal error: only the reference to the server log."""
    return f"internal error (reference {reference}; the server log has the details)"


def _chosen_id(scope: Scope) -> str:
    for key, value in scope.get("headers", ()):
        if key == _HEADER_KEY:
            text = value.decode("latin-1")
            return text if _SAFE.fullmatch(text) else new_request_id()
    return new_request_id()


class RequestIdMiddleware:
    """Give every HTTP request an id, answer with it in ``X-Request-ID`` (see the module docstring)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Run the request with its id; a 500 naming the id when the application raised before answering."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        request_id = _chosen_id(scope)
        scope.setdefault("state", {})["request_id"] = request_id
        header = (_HEADER_KEY, request_id.encode("latin-1"))
        started = False

        async def send_with_id(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                message = {**message, "headers": [*message.get("headers", ()), header]}
            await send(message)

        token = _current.set(request_id)
        try:
            await self.app(scope, receive, send_with_id)
        except Exception as err:
            where = (scope.get("method"), scope.get("path"))
            logger.error("%s %s failed (reference %s)", *where, request_id, exc_info=err)
            if started:
                raise
            body = json.dumps({"detail": internal_error_detail(request_id)}).encode("utf-8")
            headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
            await send_with_id({"type": "http.response.start", "status": 500, "headers": headers})
            await send_with_id({"type": "http.response.body", "body": body})
        finally:
            _current.reset(token)

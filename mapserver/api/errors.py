"""The one place where errors become HTTP responses: ``{"detail": "..."}`` with the right status.

``mapserver.errors`` carries each class's status (``InputError`` 400, ``NotFoundError`` 404,
``ConflictError`` 409, anything else 500); this module adds the API's own members (413, 415, 401, 403,
408, 503 with ``Retry-After``),
turns request validation failures into 422 with a one-line detail, and keeps 5xx bodies free of
internals: ``internal error (reference R; ...)``, where R is the request's id (``X-Request-ID``,
:mod:`mapserver.api.requestid`) that the server log shows beside the message and traceback.
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from mapserver.api.requestid import current_request_id, internal_error_detail, new_request_id
from mapserver.errors import InputError, MapServerError

logger = logging.getLogger(__name__)


class PayloadTooLargeError(InputError):
    """The upload is larger than the server accepts (HTTP 413)."""

    http_status = 413


class UnsupportedMediaError(InputError):
    """The request body is not ``multipart/form-data`` (HTTP 415)."""

    http_status = 415


class AuthenticationError(MapServerError):
    """No bearer token, or one the server does not know (HTTP 401 with ``WWW-Authenticate``)."""

    http_status = 401

    def __init__(self, message: str, *, invalid_token: bool = False) -> None:
        super().__init__(message)
        self.invalid_token = invalid_token


class PermissionDeniedError(MapServerError):
    """A valid token whose scope does not allow the request (HTTP 403)."""

    http_status = 403


class RequestTimeoutError(InputError):
    """The client sent nothing for longer than the server waits (HTTP 408; the connection is closed)."""

    http_status = 408


class BusyError(MapServerError):
    """The server runs as many requests of this kind as it allows (HTTP 503 with ``Retry-After``).

    The message says what is busy; unlike other 5xx answers it carries no internals and is shown as it is.
    """

    http_status = 503

    def __init__(self, message: str, *, retry_after_s: int) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


def _validation_detail(err: RequestValidationError) -> str:
    parts = []
    for item in err.errors()[:5]:
        where = ".".join(str(p) for p in item.get("loc", ()) if p != "body")
        parts.append(f"{where}: {item.get('msg', 'invalid')}" if where else str(item.get("msg", "invalid")))
    return "; ".join(parts) or "invalid request"


async def _mapserver_error(request: Request, err: Exception) -> JSONResponse:
    assert isinstance(err, MapServerError)
    status = int(getattr(err, "http_status", 500))
    headers: dict[str, str] = {}
    if isinstance(err, AuthenticationError):
        headers["WWW-Authenticate"] = 'Bearer error="invalid_token"' if err.invalid_token else "Bearer"
    if isinstance(err, RequestTimeoutError):
        headers["Connection"] = "close"
    if isinstance(err, BusyError):
        headers["Retry-After"] = str(err.retry_after_s)
    elif status >= 500:
        return _internal(request, err)
    return JSONResponse({"detail": str(err)}, status_code=status, headers=headers)


def _internal(request: Request, err: Exception) -> JSONResponse:
    """Log ``err`` under the request's id and answer 500 with only that id."""
    reference = getattr(request.state, "request_id", None) or current_request_id() or new_request_id()
    logger.error("%s %s failed (reference %s): %s", request.method, request.url.path, reference, err, exc_info=err)
    return JSONResponse({"detail": internal_error_detail(reference)}, status_code=500)


async def _validation_error(request: Request, err: Exception) -> JSONResponse:
    del request
    assert isinstance(err, RequestValidationError)
    return JSONResponse({"detail": _validation_detail(err)}, status_code=422)


async def _http_error(request: Request, err: Exception) -> JSONResponse:
    del request
    assert isinstance(err, StarletteHTTPException)
    detail = err.detail if isinstance(err.detail, str) else str(err.detail)
    return JSONResponse({"detail": detail}, status_code=err.status_code, headers=getattr(err, "headers", None))


async def _unexpected_error(request: Request, err: Exception) -> JSONResponse:
    return _internal(request, err)


def install_error_handlers(app: FastAPI) -> None:
    """Register the handlers that turn every error into ``{"detail": ...}`` with its status."""
    app.add_exception_handler(MapServerError, _mapserver_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(Exception, _unexpected_error)

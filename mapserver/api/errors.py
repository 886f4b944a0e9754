"""The one place where errors become HTTP responses: ``{"detail": "..."}`` with the right status.

``mapserver.errors`` carries each class's status (``InputError`` 400, ``NotFoundError`` 404,
``ConflictError`` 409, ``LimitError`` 413, anything else 500), and the engine's ``core.config.ConfigError`` (a
bad preset or parameter) is answered as an ``InputError`` (400); this module adds the API's own members
(413, 415, 401, 403, 408, 503 with ``Retry-After``, 507), turns request validation failures into 422 with a
one-line detail, adds ``"limit"`` (the limit's name in ``GET /v1/limits``) to the body of a refusal by a limit,
and keeps 5xx bodies free of internals: ``internal error (reference R; ...)``, where R is the request's id
(``X-Request-ID``, :mod:`mapserver.api.requestid`) that the server log shows beside the message and traceback.
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from core.config import ConfigError
from mapserver.api.requestid import current_request_id, internal_error_detail, new_request_id
from mapserver.errors import InputError, LimitError, MapServerError

logger = logging.getLogger(__name__)


class PayloadTooLargeError(LimitError):
    """The upload is larger than the server accepts (HTTP 413, limit ``max_upload_bytes``)."""

    def __init__(self, message: str, *, limit: str = "max_upload_bytes") -> None:
        super().__init__(message, limit=limit)


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


class InsufficientStorageError(MapServerError):
    """The server's disk is full: the upload cannot be stored now (HTTP 507, the server's fault, not the client's)."""

    http_status = 507


class ServerFilesError(MapServerError):
    """The server could not read or write its own files (HTTP 500; the cause goes to the log only)."""


STORAGE_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})
"""File-system errors that mean "no room to store this": answered 507."""
SERVER_FAULT_ERRNOS = frozenset({errno.EIO, errno.EROFS, errno.EACCES, errno.EPERM, errno.EMFILE, errno.ENFILE,
                                 errno.ENOMEM, errno.EBADF})  # fmt: skip
"""File-system errors on the server's own files that are never the client's fault: answered 500. (Not
``ENOENT``: a bag directory uploaded without one of its files is the client's fault.)"""
STORAGE_FULL_DETAIL = "insufficient storage: the server has no room left to store this upload; try again later"


def _causes(err: BaseException) -> list[BaseException]:
    """Return ``err`` and the errors it was raised from or while handling, nearest first."""
    chain: list[BaseException] = []
    current: BaseException | None = err
    while current is not None and current not in chain and len(chain) < 16:
        chain.append(current)
        current = current.__cause__ or current.__context__
    return chain


def raise_server_fault(err: BaseException, *, doing: str, where: Path) -> None:
    """Raise the server's own error instead of ``err`` when the server's file system caused it; else return.

    A full disk (``ENOSPC``, ``EDQUOT``, ``EFBIG`` anywhere in the chain of causes) raises
    :class:`InsufficientStorageError` (507) after one log line for the operator (``doing``, ``where``, free
    bytes); another failure of the server's own files (``EIO``, ``EROFS``, ``EACCES``, ...) raises
    :class:`ServerFilesError` (500, no internals in the body), even when a reader wrapped it as the
    client's :class:`~mapserver.errors.InputError`.
    """
    for cause in _causes(err):
        if not isinstance(cause, OSError) or cause.errno is None:
            continue
        if cause.errno in STORAGE_FULL_ERRNOS:
            free = shutil.disk_usage(where).free if where.exists() else -1
            logger.error("disk full while %s in %s (%s; %d bytes free once the partial upload was removed): "
                         "answered 507; free space there", doing, where, os.strerror(cause.errno), free)  # fmt: skip
            raise InsufficientStorageError(STORAGE_FULL_DETAIL) from err
        if cause.errno in SERVER_FAULT_ERRNOS:
            msg = f"the server could not read or write its files while {doing}"
            raise ServerFilesError(msg) from err


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
    body = {"detail": str(err)}
    if isinstance(err, LimitError):
        body["limit"] = err.limit
    return JSONResponse(body, status_code=status, headers=headers)


def _internal(request: Request, err: Exception) -> JSONResponse:
    """Log ``err`` under the request's id and answer 500 with only that id."""
    reference = getattr(request.state, "request_id", None) or current_request_id() or new_request_id()
    logger.error("%s %s failed (reference %s): %s", request.method, request.url.path, reference, err, exc_info=err)
    return JSONResponse({"detail": internal_error_detail(reference)}, status_code=500)


async def _config_error(request: Request, err: Exception) -> JSONResponse:
    """400 with the message: a bad preset or parameter is the client's input."""
    del request
    return JSONResponse({"detail": str(err)}, status_code=InputError.http_status)


async def _storage_error(request: Request, err: Exception) -> JSONResponse:
    """507 with the cause in REST words (the operator's log line was written where the error was found)."""
    del request
    return JSONResponse({"detail": str(err)}, status_code=507)


async def _validation_error(request: Request, err: Exception) -> JSONResponse:
    del request
    assert isinstance(err, RequestValidationError)
    return JSONResponse({"detail": _validation_detail(err)}, status_code=422)


async def _http_error(request: Request, err: Exception) -> JSONResponse:
    assert isinstance(err, StarletteHTTPException)
    if err.status_code >= 500:  # whatever raised it, a 5xx body names only the request's reference
        return _internal(request, err)
    detail = err.detail if isinstance(err.detail, str) else str(err.detail)
    return JSONResponse({"detail": detail}, status_code=err.status_code, headers=getattr(err, "headers", None))


async def _unexpected_error(request: Request, err: Exception) -> JSONResponse:
    return _internal(request, err)


def install_error_handlers(app: FastAPI) -> None:
    """Register the handlers that turn every error into ``{"detail": ...}`` with its status."""
    app.add_exception_handler(MapServerError, _mapserver_error)
    app.add_exception_handler(InsufficientStorageError, _storage_error)
    app.add_exception_handler(ConfigError, _config_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(Exception, _unexpected_error)

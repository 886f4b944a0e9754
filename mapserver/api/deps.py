"""Request dependencies: the services, and bearer-token access (``ReadAccess``, ``WriteAccess``)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from mapserver.api.errors import AuthenticationError, PermissionDeniedError
from mapserver.api.services import Services
from mapserver.api.settings import Settings
from mapserver.store.tokens import TokenRecord, authenticate_token

bearer_scheme = HTTPBearer(
    auto_error=False,
    description="`Authorization: Bearer <token>` (create one with `mapserver token create --scope read|write`)",
)


async def get_services(request: Request) -> Services:
    """Return the running application's services."""
    services: Services = request.app.state.services
    return services


ServicesDep = Annotated[Services, Depends(get_services)]


async def get_settings(services: ServicesDep) -> Settings:
    """Return the server's settings."""
    return services.settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


def _token(request: Request, services: Services) -> TokenRecord | None:
    """Return the request's valid token, None when it sent none; 401 for a malformed, unknown, revoked or expired one.

    Dependencies are ``async``, so this runs on the event loop: one indexed lookup costs less than the
    worker-thread hop FastAPI gives every sync dependency (twice the /path p99 under load; issue 6).
    """
    header = request.headers.get("authorization")
    if header is None:
        return None
    scheme, _, value = header.strip().partition(" ")
    if scheme.lower() != "bearer" or not value.strip():
        msg = "the Authorization header must be 'Bearer <token>'"
        raise AuthenticationError(msg, invalid_token=True)
    with services.db.read() as conn:
        found = authenticate_token(conn=conn, token=value.strip())
    if found is None:
        msg = "unknown token"
        raise AuthenticationError(msg, invalid_token=True)
    if found.refusal is not None:  # revoked or expired: named by its id, never by its characters
        raise AuthenticationError(found.refusal, invalid_token=True)
    last_used = None if found.last_used_at is None else found.last_used_at.timestamp()
    services.touch_token(found.record.id, last_used)
    return found.record


async def require_read(
    request: Request,
    services: ServicesDep,
    _credentials: Annotated[HTTPAuthorizationCredentials | None, Security(bearer_scheme)],
) -> TokenRecord | None:
    """Allow a read: any valid token, or none when the server allows anonymous reads (401 otherwise)."""
    token = _token(request, services)
    if token is None and not services.settings.allow_anonymous_reads:
        msg = "this request needs a token: send 'Authorization: Bearer <token>'"
        raise AuthenticationError(msg)
    return token


async def require_write(
    request: Request,
    services: ServicesDep,
    _credentials: Annotated[HTTPAuthorizationCredentials | None, Security(bearer_scheme)],
) -> TokenRecord:
    """Allow a write: a valid token with scope ``write`` (401 without or with a bad one, 403 for ``read``)."""
    token = _token(request, services)
    if token is None:
        msg = "writing needs a token with scope 'write': send 'Authorization: Bearer <token>'"
        raise AuthenticationError(msg)
    if token.scope != "write":
        msg = f"token {token.id} has scope {token.scope!r}; this request needs scope 'write'"
        raise PermissionDeniedError(msg)
    return token


ReadAccess = Annotated[TokenRecord | None, Depends(require_read)]
WriteAccess = Annotated[TokenRecord, Depends(require_write)]

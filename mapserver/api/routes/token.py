"""``GET /v1/token``: what the request's token may do (the viewer shows its write actions for a write token)."""

from __future__ import annotations

from fastapi import APIRouter

from mapserver.api.deps import ReadAccess
from mapserver.api.errors import AuthenticationError
from mapserver.api.routes.maps import AUTH_ERRORS
from mapserver.api.schemas import TokenPublic

router = APIRouter(prefix="/v1/token", tags=["token"])


@router.get("", operation_id="read_token", response_model=TokenPublic, responses=AUTH_ERRORS)
async def read_token(token: ReadAccess) -> TokenPublic:
    """Return the id, scope, label and expiry of the token sent (401 without one)."""
    if token is None:
        msg = "no token sent: send 'Authorization: Bearer <token>'"
        raise AuthenticationError(msg)
    return TokenPublic(id=token.id, scope=token.scope, label=token.label, expires_at=token.expires_at)

"""REST API tokens (issue 6): created once, shown once, stored as SHA-256 only."""

from __future__ import annotations

import hashlib
import hmac
import secrets
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import Connection, insert, select, update

from mapserver.errors import InputError, NotFoundError
from mapserver.store.models import TOKEN_SCOPES, ApiToken, utcnow

TOKEN_PREFIX = "msk_"


@dataclass(frozen=True, slots=True)
class TokenRecord:
    """A stored token (never the token itself)."""

    id: int
    prefix: str
    scope: str
    label: str | None
    created_at: datetime
    revoked_at: datetime | None


def hash_token(token: str) -> str:
    """Return the hex SHA-256 of a token (what the database stores)."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def create_token(*, conn: Connection, scope: str, label: str | None = None) -> tuple[str, TokenRecord]:
    """Create a token with scope ``read`` or ``write``; return (the token, its record).

    Raises:
        InputError: unknown scope.
    """
    if scope not in TOKEN_SCOPES:
        msg = f"token scope must be one of {', '.join(TOKEN_SCOPES)}, got {scope!r}"
        raise InputError(msg)
    token = TOKEN_PREFIX + secrets.token_urlsafe(32)
    now = utcnow()
    token_id = conn.execute(
        insert(ApiToken)
        .values(token_sha256=hash_token(token), prefix=token[:12], scope=scope, label=label, created_at=now)
        .returning(ApiToken.id)
    ).scalar_one()
    return token, TokenRecord(int(token_id), token[:12], scope, label, now, None)


def verify_token(*, conn: Connection, token: str) -> TokenRecord | None:
    """Return the record of a valid (known, not revoked) token, else None."""
    row = conn.execute(
        select(ApiToken.id, ApiToken.prefix, ApiToken.scope, ApiToken.label, ApiToken.created_at, ApiToken.revoked_at)
        .where(ApiToken.token_sha256 == hash_token(token))
    ).first()
    if row is None or row[5] is not None:
        return None
    return TokenRecord(int(row[0]), str(row[1]), str(row[2]), row[3], row[4], row[5])


def revoke_token(*, conn: Connection, token_id: int) -> None:
    """Revoke a token.

    Raises:
        NotFoundError: no such token.
    """
    result = conn.execute(update(ApiToken).where(ApiToken.id == token_id).values(revoked_at=utcnow()))
    if result.rowcount != 1:
        msg = f"no token with id {token_id!r}"
        raise NotFoundError(msg)


# ------------------------------------------------------------------------------------ API authentication
TOKEN_MAX_LENGTH = 256
"""Longer bearer strings are refused without a database lookup."""

LAST_USED_RESOLUTION_S = 300.0
"""``last_used_at`` is written at most this often per token (reads stay read-only most of the time)."""


@dataclass(frozen=True, slots=True)
class AuthenticatedToken:
    """A token that :func:`authenticate_token` accepted: its record and when it was last marked used."""

    record: TokenRecord
    last_used_at: datetime | None


def authenticate_token(*, conn: Connection, token: str) -> AuthenticatedToken | None:
    """Return the valid (known, not revoked) token ``token``, else None.

    The lookup is by SHA-256 (an index hit on ``token_sha256``), and the stored digest is compared
    again with :func:`hmac.compare_digest`, so the answer takes the same time whatever prefix of a
    stored digest the presented token shares. Tokens are 256-bit random strings, which is why an
    unsalted fast hash is enough: there is no dictionary to guess from, and a leaked table of
    digests gives no usable token.
    """
    if not token or len(token) > TOKEN_MAX_LENGTH:
        return None
    digest = hash_token(token)
    row = conn.execute(
        select(
            ApiToken.id, ApiToken.prefix, ApiToken.scope, ApiToken.label, ApiToken.created_at, ApiToken.revoked_at,
            ApiToken.token_sha256, ApiToken.last_used_at,
        ).where(ApiToken.token_sha256 == digest)
    ).first()  # fmt: skip
    if row is None or not hmac.compare_digest(str(row[6]).encode(), digest.encode()) or row[5] is not None:
        return None
    return AuthenticatedToken(TokenRecord(int(row[0]), str(row[1]), str(row[2]), row[3], row[4], row[5]), row[7])


def mark_token_used(*, conn: Connection, token_id: int) -> None:
    """Record that a token was just used (``last_used_at``)."""
    conn.execute(update(ApiToken).where(ApiToken.id == token_id).values(last_used_at=utcnow()))


def list_tokens(*, conn: Connection) -> list[TokenRecord]:
    """Return every token's record (never the token), oldest first."""
    rows = conn.execute(
        select(ApiToken.id, ApiToken.prefix, ApiToken.scope, ApiToken.label, ApiToken.created_at, ApiToken.revoked_at)
        .order_by(ApiToken.id)
    ).all()
    return [TokenRecord(int(r[0]), str(r[1]), str(r[2]), r[3], r[4], r[5]) for r in rows]

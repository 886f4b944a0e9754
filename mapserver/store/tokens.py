"""REST API tokens (issue 6): created once, shown once, stored as SHA-256 only; optionally expiring."""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import Connection, insert, select, update

from mapserver.errors import InputError, NotFoundError
from mapserver.store.models import TOKEN_SCOPES, ApiToken, utcnow

TOKEN_PREFIX = "msk_"


@dataclass(frozen=True, slots=True)
class TokenRecord:
    """A stored token (never the token itself); ``expires_at`` None: it never expires."""

    id: int
    prefix: str
    scope: str
    label: str | None
    created_at: datetime
    revoked_at: datetime | None
    expires_at: datetime | None = None


def hash_token(token: str) -> str:
    """Return the hex SHA-256 of a token (what the database stores)."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def create_token(
    *, conn: Connection, scope: str, label: str | None = None, expires_at: datetime | None = None
) -> tuple[str, TokenRecord]:
    """Create a token with scope ``read`` or ``write``; return (the token, its record).

    ``expires_at``: when the token stops working (None: never).

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
        .values(token_sha256=hash_token(token), prefix=token[:12], scope=scope, label=label, created_at=now,
                expires_at=expires_at)
        .returning(ApiToken.id)
    ).scalar_one()  # fmt: skip
    stored = _record(conn.execute(select(*_RECORD).where(ApiToken.id == token_id)).one())
    return token, stored


_DURATION = re.compile(r"(\d{1,6})([smhdw])")
_UNITS = {"s": "seconds", "m": "minutes", "h": "hours", "d": "days", "w": "weeks"}


def parse_duration(text: str) -> timedelta:
    """Return the duration ``text`` gives: a positive whole number and a unit, ``s``, ``m``, ``h``, ``d`` or ``w``.

    Raises:
        InputError: anything else (``30d``, ``12h`` and ``90m`` are durations; ``0d``, ``1.5d``, ``30`` are not).
    """
    found = _DURATION.fullmatch(text.strip())
    if found is None or int(found.group(1)) == 0:
        msg = f"a duration is a positive whole number and a unit s, m, h, d or w (e.g. 30d), got {text!r}"
        raise InputError(msg)
    return timedelta(**{_UNITS[found.group(2)]: int(found.group(1))})


_RECORD = (
    ApiToken.id, ApiToken.prefix, ApiToken.scope, ApiToken.label, ApiToken.created_at, ApiToken.revoked_at,
    ApiToken.expires_at,
)  # fmt: skip


def _record(row: Any) -> TokenRecord:
    return TokenRecord(int(row[0]), str(row[1]), str(row[2]), row[3], row[4], row[5], row[6])


def verify_token(*, conn: Connection, token: str) -> TokenRecord | None:
    """Return the record of a valid (known, not revoked, not expired) token, else None."""
    row = conn.execute(select(*_RECORD).where(ApiToken.token_sha256 == hash_token(token))).first()
    if row is None:
        return None
    record = _record(row)
    return None if token_refusal(record) is not None else record


def token_refusal(record: TokenRecord, now: datetime | None = None) -> str | None:
    """Return why a known token is refused (revoked, or expired at ``now``) naming its id; None when it is valid."""
    if record.revoked_at is not None:
        return f"token {record.id} was revoked"
    if record.expires_at is not None and record.expires_at <= (now or utcnow()):
        return f"token {record.id} expired at {record.expires_at.isoformat(timespec='seconds')}"
    return None


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

LAST_USED_RESOLUTION_S = 60.0
"""``last_used_at`` is written at most this often per token (reads stay read-only most of the time)."""


@dataclass(frozen=True, slots=True)
class AuthenticatedToken:
    """A token :func:`authenticate_token` found: its record, when it was last marked used, and its refusal.

    ``refusal``: why it is refused (revoked or expired, naming its id); None when it is valid.
    """

    record: TokenRecord
    last_used_at: datetime | None
    refusal: str | None = None


def authenticate_token(*, conn: Connection, token: str) -> AuthenticatedToken | None:
    """Return the stored token ``token`` (check its ``refusal``), or None when no stored token is ``token``.

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
        select(*_RECORD, ApiToken.token_sha256, ApiToken.last_used_at).where(ApiToken.token_sha256 == digest)
    ).first()
    if row is None or not hmac.compare_digest(str(row[7]).encode(), digest.encode()):
        return None
    record = _record(row)
    return AuthenticatedToken(record, row[8], token_refusal(record))


def mark_token_used(*, conn: Connection, token_id: int) -> None:
    """Record that a token was just used (``last_used_at``)."""
    conn.execute(update(ApiToken).where(ApiToken.id == token_id).values(last_used_at=utcnow()))


def list_tokens(*, conn: Connection) -> list[TokenRecord]:
    """Return every token's record (never the token), oldest first."""
    rows = conn.execute(select(*_RECORD).order_by(ApiToken.id)).all()
    return [_record(r) for r in rows]

"""API tables (issue 6): hashed tokens and the job queue."""

from __future__ import annotations

import hashlib

import pytest
import sqlalchemy as sa

from mapserver.errors import InputError, NotFoundError
from mapserver.store import Database
from mapserver.store.jobs import claim_next_job, create_job, fail_job, finish_job, get_job, set_job_progress
from mapserver.store.models import ApiToken
from mapserver.store.tokens import create_token, revoke_token, verify_token


def test_tokens_are_stored_hashed_and_can_be_revoked(db: Database) -> None:
    with db.write() as conn:
        token, record = create_token(conn=conn, scope="write", label="ci")
    with db.read() as conn:
        stored = conn.execute(sa.select(ApiToken.token_sha256, ApiToken.prefix)).all()
        assert stored == [(hashlib.sha256(token.encode()).hexdigest(), token[:12])]
        assert verify_token(conn=conn, token=token) == record
        assert verify_token(conn=conn, token=token + "x") is None
    with db.write() as conn:
        revoke_token(conn=conn, token_id=record.id)
        with pytest.raises(NotFoundError):
            revoke_token(conn=conn, token_id=record.id + 1)
        with pytest.raises(InputError, match="scope"):
            create_token(conn=conn, scope="admin")
    with db.read() as conn:
        assert verify_token(conn=conn, token=token) is None


def test_jobs_are_claimed_once_in_order_and_finish(db: Database) -> None:
    with db.write() as conn:
        first = create_job(conn=conn, upload_path="/up/1.bag", upload_sha256="1" * 64, map_name="lab")
        second = create_job(conn=conn, upload_path="/up/2.bag")
    with db.write() as conn:
        claimed = claim_next_job(conn=conn)
        assert claimed is not None and claimed.id == first.id and claimed.status == "running"
        assert claimed.lease_token == 1
        assert set_job_progress(conn=conn, job_id=first.id, progress=1.7, lease_token=1)
        assert get_job(conn=conn, job_id=first.id).progress == 1.0
        assert claim_next_job(conn=conn).id == second.id  # type: ignore[union-attr]
        assert claim_next_job(conn=conn) is None
        assert finish_job(conn=conn, job_id=first.id, session_id=None, map_id=None, lease_token=1)
        assert fail_job(conn=conn, job_id=second.id, error="bad\nbag:  corrupt", lease_token=1)
    with db.read() as conn:
        assert get_job(conn=conn, job_id=first.id).status == "done"
        failed = get_job(conn=conn, job_id=second.id)
        assert (failed.status, failed.error) == ("failed", "bad bag: corrupt")
        with pytest.raises(NotFoundError):
            get_job(conn=conn, job_id=999)


def test_an_expired_token_is_refused_by_its_id_and_a_fresh_one_is_valid(db: Database) -> None:
    from datetime import timedelta

    from mapserver.store.models import utcnow
    from mapserver.store.tokens import authenticate_token, parse_duration

    now = utcnow()
    with db.write() as conn:
        old, old_record = create_token(conn=conn, scope="read", expires_at=now - timedelta(seconds=1))
        fresh, fresh_record = create_token(conn=conn, scope="read", expires_at=now + parse_duration("30d"))
        forever, _ = create_token(conn=conn, scope="read")
    with db.read() as conn:
        expired = authenticate_token(conn=conn, token=old)
        assert expired is not None and expired.refusal is not None
        assert expired.refusal.startswith(f"token {old_record.id} expired at ")
        assert old not in expired.refusal and old[:12] not in expired.refusal
        assert verify_token(conn=conn, token=old) is None
        valid = authenticate_token(conn=conn, token=fresh)
        assert valid is not None and valid.refusal is None
        assert valid.record.expires_at is not None
        assert abs((valid.record.expires_at - now - timedelta(days=30)).total_seconds()) < 1
        assert verify_token(conn=conn, token=fresh) == fresh_record
        assert verify_token(conn=conn, token=forever) is not None


def test_durations_are_a_number_and_a_unit() -> None:
    from datetime import timedelta

    from mapserver.store.tokens import parse_duration

    assert parse_duration("30d") == timedelta(days=30)
    assert parse_duration("12h") == timedelta(hours=12)
    assert parse_duration("2w") == timedelta(weeks=2)
    for bad in ("0d", "1.5d", "30", "d", "-1d", "30 days"):
        with pytest.raises(InputError, match="duration"):
            parse_duration(bad)

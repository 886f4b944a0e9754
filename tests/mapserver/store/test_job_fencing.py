"""Fencing tokens of job leases (``jobs.lease_token``, migration 0007), on SQLite and PostgreSQL.

Each must-happen is paired with its must-not-happen: the holder's write lands, a stale holder's changes
nothing; an expired lease is taken over, a live one is not; the migration keeps the rows it extends.
"""

from __future__ import annotations

from datetime import timedelta

import sqlalchemy as sa

from mapserver.store import Database, downgrade, upgrade
from mapserver.store.jobs import (
    claim_next_job,
    claim_next_job_excluding,
    create_job,
    fail_job,
    finish_job,
    get_job,
    job_uploads,
    recover_interrupted_jobs,
    renew_job_leases,
    requeue_job,
    set_job_progress,
)
from mapserver.store.models import Job, utcnow


def test_a_stale_holder_writes_nothing_and_the_new_holder_finishes_once(db: Database) -> None:
    with db.write() as conn:
        job_id = create_job(conn=conn, upload_path="/up/a/x.bag", map_name="a").id
        first = claim_next_job_excluding(conn=conn, busy_maps=(), owner="s1", lease_s=30)
    assert first is not None and first.lease_token == 1
    with db.write() as conn:
        assert set_job_progress(conn=conn, job_id=job_id, progress=0.25, lease_token=1)  # the holder writes
        # a second server takes the job over (its holder looked dead): the token moves on
        assert recover_interrupted_jobs(conn=conn, max_attempts=3) == ([job_id], [])
        second = claim_next_job(conn=conn, owner="s2", lease_s=30)
    assert second is not None and second.lease_token == 3 and second.options == {"attempts": 1}
    with db.write() as conn:
        # the first holder, still running, is fenced off: none of its writes changes the row
        assert not set_job_progress(conn=conn, job_id=job_id, progress=0.9, lease_token=1)
        assert not finish_job(conn=conn, job_id=job_id, session_id=None, map_id=None, lease_token=1)
        assert not fail_job(conn=conn, job_id=job_id, error="stale", lease_token=1)
        assert not requeue_job(conn=conn, job_id=job_id, lease_token=1)
        assert renew_job_leases(conn=conn, leases={job_id: 1}, lease_s=30) == [job_id]
        record = get_job(conn=conn, job_id=job_id)
        assert (record.status, record.progress, record.error) == ("running", 0.0, None)
        # the new holder's writes land, and the job is finished once
        assert renew_job_leases(conn=conn, leases={job_id: 3}, lease_s=30) == []
        assert set_job_progress(conn=conn, job_id=job_id, progress=0.5, lease_token=3)
        assert finish_job(conn=conn, job_id=job_id, session_id=None, map_id=None, lease_token=3)
        assert not finish_job(conn=conn, job_id=job_id, session_id=None, map_id=None, lease_token=3)
        assert not set_job_progress(conn=conn, job_id=job_id, progress=0.1, lease_token=3)  # done is final
    with db.read() as conn:
        done = get_job(conn=conn, job_id=job_id)
        lease = conn.execute(sa.select(Job.lease_owner, Job.lease_expires_at).where(Job.id == job_id)).one()
    assert (done.status, done.progress, done.lease_token) == ("done", 1.0, 3)
    assert tuple(lease) == ("s2", None)


def test_only_expired_leases_are_taken_over_unless_the_caller_is_alone(db: Database) -> None:
    with db.write() as conn:
        live = create_job(conn=conn, upload_path="/up/a/x.bag", map_name="a").id
        lapsed = create_job(conn=conn, upload_path="/up/b/x.bag", map_name="b").id
        legacy = create_job(conn=conn, upload_path="/up/c/x.bag", map_name="c").id
        for _ in range(3):
            claim_next_job(conn=conn, owner="s1", lease_s=30)
        conn.execute(sa.update(Job).where(Job.id == lapsed).values(lease_expires_at=utcnow() - timedelta(seconds=1)))
        conn.execute(sa.update(Job).where(Job.id == legacy).values(lease_expires_at=None))  # claimed before 0007
    with db.write() as conn:
        assert recover_interrupted_jobs(conn=conn, max_attempts=3, expired_only=True) == ([lapsed, legacy], [])
        assert get_job(conn=conn, job_id=live).status == "running"  # a live lease is left to its holder
        assert set_job_progress(conn=conn, job_id=live, progress=0.5, lease_token=1)
        # a server that knows it is alone on the database (its server lock) takes every running job
        assert recover_interrupted_jobs(conn=conn, max_attempts=1) == ([], [live])
        failed = get_job(conn=conn, job_id=live)
    assert failed.status == "failed" and "giving up" in (failed.error or "") and failed.lease_token == 2


def test_job_uploads_lists_finished_jobs_by_age(db: Database) -> None:
    now = utcnow()
    with db.write() as conn:
        ids = [create_job(conn=conn, upload_path=f"/up/{k}/x.bag").id for k in range(4)]
        for job_id, status, age_days in zip(ids, ("done", "failed", "done", "queued"), (10, 10, 1, 10), strict=True):
            finished = None if status == "queued" else now - timedelta(days=age_days)
            conn.execute(sa.update(Job).where(Job.id == job_id).values(status=status, finished_at=finished))
    with db.read() as conn:
        old = job_uploads(conn=conn, statuses=("done", "failed"), finished_before=now - timedelta(days=7))
        live = job_uploads(conn=conn, statuses=("queued", "running"))
        every = job_uploads(conn=conn)
    assert old == [(ids[0], "done", "/up/0/x.bag"), (ids[1], "failed", "/up/1/x.bag")]
    assert live == [(ids[3], "queued", "/up/3/x.bag")]
    assert [row[0] for row in every] == ids


def test_migration_0007_adds_the_token_to_existing_jobs_and_drops_it_again(db_url: str) -> None:
    from mapserver.store import Database, create_db_engine

    with Database(create_db_engine(db_url)) as db:
        assert upgrade(db, "0006") == "0006"
        now = utcnow()
        with db.write() as conn:
            conn.execute(
                sa.text("INSERT INTO jobs (status, progress, upload_path, created_at, updated_at, lease_owner) "
                        "VALUES ('running', 0.5, '/up/a/x.bag', :now, :now, 'old-server')"),
                {"now": now},
            )  # fmt: skip
        assert upgrade(db, "0007") == "0007"
        with db.write() as conn:
            (job_id,) = conn.execute(sa.text("SELECT id FROM jobs")).scalars().all()
            record = get_job(conn=conn, job_id=job_id)
            assert (record.status, record.progress, record.lease_token) == ("running", 0.5, 0)
            # the job of a server from before the migration is recovered like any other
            assert recover_interrupted_jobs(conn=conn, max_attempts=3, expired_only=True) == ([job_id], [])
            assert get_job(conn=conn, job_id=job_id).lease_token == 1
        assert downgrade(db, "0006") == "0006"
        with db.read() as conn:
            columns = {c["name"] for c in sa.inspect(conn).get_columns("jobs")}
            count = conn.execute(sa.text("SELECT count(*) FROM jobs")).scalar_one()
        assert "lease_token" not in columns and count == 1
        assert upgrade(db, "0007") == "0007"

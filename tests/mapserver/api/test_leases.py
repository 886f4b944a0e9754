"""Leases and per-map locks of the Celery engine, in one process on real PostgreSQL (issue 15)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import sqlalchemy as sa

from mapserver.api import celery_worker
from mapserver.api.worker import JobOutcome
from mapserver.cli import main
from mapserver.store import Database, open_database
from mapserver.store.jobs import create_job, get_job
from mapserver.store.leases import MapLock, claim_map_job, complete_job, due_job_maps, renew_lease
from mapserver.store.models import Job
from tests.mapserver.store.conftest import _pg_drop, _pg_schema_url, pg_unreachable

pytestmark = pytest.mark.postgres


@pytest.fixture
def pg() -> Iterator[tuple[str, Database]]:
    reason = pg_unreachable()
    if reason is not None:
        pytest.skip(reason)
    url, schema = _pg_schema_url()
    db = open_database(url)
    try:
        yield url, db
    finally:
        db.dispose()
        _pg_drop(schema)


def _queue(db: Database, *maps: str | None) -> list[int]:
    with db.write() as conn:
        return [create_job(conn=conn, upload_path=f"/x/{k}.bag", map_name=m, options={"attempts": 0}).id
                for k, m in enumerate(maps)]  # fmt: skip


def test_the_map_lock_admits_one_holder_and_a_dead_connection_frees_it(pg: tuple[str, Database]) -> None:
    url, db = pg
    other = open_database(url)
    try:
        first, second, third = MapLock(db, "a"), MapLock(other, "a"), MapLock(other, "b")
        assert first.try_acquire() and first.alive()
        assert not second.try_acquire()  # one holder per map, across connections (processes)
        assert third.try_acquire()  # another map is free
        with db.engine.connect() as conn:  # the holder's session dies (as with kill -9): the lock is free
            pid = first._conn.connection.dbapi_connection.info.backend_pid  # type: ignore[union-attr]
            conn.execute(sa.text("SELECT pg_terminate_backend(:p)"), {"p": pid})
        assert not first.alive()
        assert second.try_acquire()
        first.release()
        second.release()
        third.release()
    finally:
        other.dispose()


def test_claims_follow_queue_order_take_over_lost_jobs_and_give_up(pg: tuple[str, Database]) -> None:
    _url, db = pg
    a1, b1, a2 = _queue(db, "a", "b", "a")
    with db.write() as conn:
        claim = claim_map_job(conn=conn, key="a", owner="w1:1", lease_s=30, max_attempts=3)
    assert claim.job is not None and (claim.job.id, claim.taken_over) == (a1, False)
    first_token = claim.job.lease_token
    # w1 dies holding a1; the next holder of the lock takes a1 over before a2 (attempts + 1)
    with db.write() as conn:
        claim = claim_map_job(conn=conn, key="a", owner="w2:7", lease_s=30, max_attempts=3)
        assert claim.job is not None and (claim.job.id, claim.taken_over) == (a1, True)
        assert claim.job.options == {"attempts": 1}
        token = claim.job.lease_token
        assert token == first_token + 1  # every claim and takeover moves the fencing token on
        assert not renew_lease(conn=conn, job_id=a1, owner="w1:1", lease_s=30, lease_token=first_token)  # lost
        assert not complete_job(conn=conn, job_id=a1, owner="w1:1", lease_token=first_token, session_id=None,
                                map_id=None, error=None)  # fmt: skip
        # the same worker name at a stale token (a restarted process reusing a pid) writes nothing either
        assert not renew_lease(conn=conn, job_id=a1, owner="w2:7", lease_s=30, lease_token=first_token)
        assert renew_lease(conn=conn, job_id=a1, owner="w2:7", lease_s=30, lease_token=token)
        # lost once more: the third loss fails it (max_attempts=3), and the claim moves on to a2
        claim_map_job(conn=conn, key="a", owner="w3:1", lease_s=30, max_attempts=3)
        claim = claim_map_job(conn=conn, key="a", owner="w4:1", lease_s=30, max_attempts=3)
        assert claim.failed == (a1,) and claim.job is not None and claim.job.id == a2
        assert complete_job(conn=conn, job_id=a2, owner="w4:1", lease_token=claim.job.lease_token, session_id=None,
                            map_id=None, error=None)  # fmt: skip
        lost, done, other = (get_job(conn=conn, job_id=i) for i in (a1, a2, b1))
        lease = conn.execute(sa.select(Job.lease_expires_at).where(Job.id == a2)).scalar_one()
    assert lost.status == "failed" and "lost 3 times" in (lost.error or "")
    assert (done.status, done.progress, lease) == ("done", 1.0, None)
    assert other.status == "queued"


_EXPIRED = sa.func.now() - sa.text("interval '1 s'")


def test_dispatch_marks_queued_jobs_once_per_window_and_redispatches_expired_leases(pg: tuple[str, Database]) -> None:
    _url, db = pg
    a, b, lone = _queue(db, "a", "b", None)
    with db.write() as conn:
        assert due_job_maps(conn=conn, redispatch_s=60) == ["a", "b", f"#job-{lone}"]
        assert due_job_maps(conn=conn, redispatch_s=60) == []  # dispatched: not again within the window
        claim_map_job(conn=conn, key="a", owner="w1:1", lease_s=30, max_attempts=3)
        conn.execute(sa.update(Job).where(Job.id == b).values(lease_expires_at=_EXPIRED))
        assert due_job_maps(conn=conn, redispatch_s=60) == ["b"]  # the window of b passed
        conn.execute(sa.update(Job).where(Job.id == a).values(lease_expires_at=_EXPIRED))
        assert due_job_maps(conn=conn, redispatch_s=60) == ["a"]  # a running job whose lease expired


def test_drain_runs_one_maps_jobs_in_order_and_maps_in_parallel(pg: tuple[str, Database],
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    url, db = pg
    spans: dict[int, tuple[str, float, float]] = {}
    lock = threading.Lock()

    def fake_execute(job: Any, **_kw: Any) -> JobOutcome:
        start = time.monotonic()
        time.sleep(0.3)
        with lock:
            spans[job.id] = (job.map_name, start, time.monotonic())
        return JobOutcome()

    monkeypatch.setattr(celery_worker, "execute_job", fake_execute)
    celery_worker.configure(celery_worker.WorkerConfig(db_url=url, name="t", lease_s=5.0))
    ids = _queue(db, "a", "a", "b", "a", "b")
    # five messages (one per job) on three workers: duplicates find the lock taken or nothing left
    threads = [threading.Thread(target=celery_worker.drain, args=(k,)) for k in ("a", "a", "b", "a", "b")]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    with db.read() as conn:
        assert [get_job(conn=conn, job_id=i).status for i in ids] == ["done"] * 5
    assert sorted(spans) == ids  # each job ran exactly once

    def overlap(x: tuple[str, float, float], y: tuple[str, float, float]) -> bool:
        return x[1] < y[2] and y[1] < x[2]

    same = [(i, j) for i in ids for j in ids if i < j and spans[i][0] == spans[j][0]]
    assert same and not any(overlap(spans[i], spans[j]) for i, j in same)
    assert any(overlap(spans[i], spans[j]) for i in ids for j in ids if spans[i][0] != spans[j][0])
    assert [i for _s, i in sorted((spans[i][1], i) for i in ids if spans[i][0] == "a")] == [ids[0], ids[1], ids[3]]


def test_celery_mode_refuses_sqlite_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    db = f"sqlite:///{tmp_path / 'x.db'}"
    assert main(["serve", "--db", db, "--jobs", "celery"]) == 2
    assert main(["worker", "--db", db]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2 and all(line.startswith("ERROR: ") and "PostgreSQL" in line for line in lines)
    assert not (tmp_path / "x.db").exists()  # refused before anything was created

"""The embedded job engine: jobs of one map run one after another, different maps in parallel; recovery."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import pytest

from mapserver.api import jobengine
from mapserver.api.worker import JobOutcome
from mapserver.store import open_database
from mapserver.store.jobs import create_job, get_job, recover_interrupted_jobs
from mapserver.store.models import Job


def test_one_map_at_a_time_and_maps_in_parallel(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    spans: dict[int, tuple[str, float, float]] = {}
    lock = threading.Lock()

    def fake_execute(job: Any, **_kw: Any) -> JobOutcome:
        start = time.monotonic()
        time.sleep(0.3)
        with lock:
            spans[job.id] = (job.map_name, start, time.monotonic())
        return JobOutcome()

    monkeypatch.setattr(jobengine, "execute_job", fake_execute)
    url = f"sqlite:///{tmp_path / 'jobs.db'}"
    with open_database(url) as db:
        with db.write() as conn:
            ids = [create_job(conn=conn, upload_path=f"/x/{k}.bag", map_name=m).id for k, m in
                   enumerate(["a", "a", "b", "a", "b"])]  # fmt: skip
        engine = jobengine.EmbeddedJobEngine(db, workers=3)
        engine.start()
        deadline = time.monotonic() + 20
        while len(spans) < len(ids) and time.monotonic() < deadline:
            time.sleep(0.05)
        engine.stop()
        with db.read() as conn:
            assert [get_job(conn=conn, job_id=i).status for i in ids] == ["done"] * 5

    def overlap(x: tuple[str, float, float], y: tuple[str, float, float]) -> bool:
        return x[1] < y[2] and y[1] < x[2]

    same = [(i, j) for i in ids for j in ids if i < j and spans[i][0] == spans[j][0]]
    assert same and not any(overlap(spans[i], spans[j]) for i, j in same)
    assert any(overlap(spans[i], spans[j]) for i in ids for j in ids if spans[i][0] != spans[j][0])
    a_jobs = sorted((spans[i][1], i) for i in ids if spans[i][0] == "a")
    assert [i for _s, i in a_jobs] == [ids[0], ids[1], ids[3]]  # queue order within a map


def test_recovery_reruns_or_fails_interrupted_jobs(tmp_path: Path) -> None:
    import sqlalchemy as sa

    url = f"sqlite:///{tmp_path / 'jobs.db'}"
    with open_database(url) as db:
        with db.write() as conn:
            fresh = create_job(conn=conn, upload_path="/x/a.bag", map_name="a").id
            tired = create_job(conn=conn, upload_path="/x/b.bag", map_name="b", options={"attempts": 2}).id
            queued = create_job(conn=conn, upload_path="/x/c.bag", map_name="c").id
            conn.execute(sa.update(Job).where(Job.id.in_([fresh, tired])).values(status="running", progress=0.4))
        with db.write() as conn:
            requeued, failed = recover_interrupted_jobs(conn=conn, max_attempts=3)
        assert (requeued, failed) == ([fresh], [tired])
        with db.read() as conn:
            a, b, c = (get_job(conn=conn, job_id=i) for i in (fresh, tired, queued))
        assert (a.status, a.progress, a.options) == ("queued", 0.0, {"attempts": 1})
        assert b.status == "failed" and "3 times" in (b.error or "")
        assert c.status == "queued"


def test_stop_interrupts_a_running_job_and_queues_it_again(tmp_path: Path) -> None:
    from tests.mapserver.api.logs import write_strip_log

    log = write_strip_log(tmp_path / "long.bag", laps=30.0)
    url = f"sqlite:///{tmp_path / 'jobs.db'}"
    with open_database(url) as db:
        with db.write() as conn:
            job = create_job(conn=conn, upload_path=str(log), map_name="long", preset="irat",
                             options={"map_given": True, "attempts": 0}).id  # fmt: skip
        engine = jobengine.EmbeddedJobEngine(db, workers=1, progress_interval_s=0.0)
        engine.start()
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            with db.read() as conn:
                if get_job(conn=conn, job_id=job).progress > 0.02:
                    break
            time.sleep(0.02)
        engine.stop()
        with db.read() as conn:
            record = get_job(conn=conn, job_id=job)
            from mapserver.store import list_maps

            assert list_maps(conn=conn) == []
        assert (record.status, record.progress) == ("queued", 0.0)

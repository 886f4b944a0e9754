"""A second server on the same database (issue 61, item 5), in one process.

Two embedded job engines on one database (SQLite and PostgreSQL): the holder of a live lease finishes its
job once and the second engine writes nothing to it; a holder whose lease lapsed is fenced off — its
progress and outcome writes change nothing, it stops, and the engine that took the job over finishes it
once. With SQLite a second server is refused at start (its server lock), and starts once the first is gone.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from mapserver.api import Settings, create_app, jobengine
from mapserver.api.lifecycle import ServerLock
from mapserver.api.worker import JobInterrupted, JobOutcome, ProgressReporter
from mapserver.errors import ConflictError
from mapserver.store import Database, open_database
from mapserver.store.jobs import claim_next_job, create_job, get_job
from tests.mapserver.api.conftest import Api
from tests.mapserver.store.conftest import _pg_drop, _pg_schema_url, pg_unreachable

FRAMES = 12
STEP_S = 0.25
LEASE_S = 1.0  # the job (3 s) outlives three leases: only renewals keep it with its holder


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[str, Database]]:
    if request.param == "sqlite":
        url = f"sqlite:///{tmp_path / 'jobs.db'}"
        with open_database(url) as db:
            yield url, db
        return
    reason = pg_unreachable()
    if reason is not None:
        pytest.skip(reason)
    url, schema = _pg_schema_url()
    try:
        with open_database(url) as db:
            yield url, db
    finally:
        _pg_drop(schema)


class Recorder:
    """A stand-in for ``execute_job`` that reports FRAMES frames, and a record of every outcome write."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.runs: list[tuple[int, str]] = []  # (fencing token, how the run ended)
        self.rejected = 0
        self.finishes: list[tuple[int, bool]] = []  # (fencing token, row changed)

    def execute(self, job: Any, *, db: Database, should_stop: Any, **_kw: Any) -> JobOutcome:
        reporter = ProgressReporter(db, job.id, interval_s=0.0, should_stop=should_stop, lease_token=job.lease_token)
        try:
            for frame in range(1, FRAMES + 1):
                time.sleep(STEP_S)
                reporter(frame, FRAMES)
        except JobInterrupted as err:
            with self.lock:
                self.runs.append((job.lease_token, type(err).__name__))
            raise
        with self.lock:
            self.runs.append((job.lease_token, "finished"))
        return JobOutcome()

    def finish(self, *, lease_token: int, **kw: Any) -> bool:
        held = REAL_FINISH(lease_token=lease_token, **kw)
        with self.lock:
            self.finishes.append((lease_token, held))
        return held


REAL_FINISH = jobengine.finish_job


@pytest.fixture
def recorder(monkeypatch: pytest.MonkeyPatch) -> Recorder:
    rec = Recorder()
    monkeypatch.setattr(jobengine, "execute_job", rec.execute)
    monkeypatch.setattr(jobengine, "finish_job", rec.finish)
    return rec


def _engine(url: str, db: Database) -> jobengine.EmbeddedJobEngine:
    return jobengine.EmbeddedJobEngine(db, workers=1, progress_interval_s=0.0, lease_s=LEASE_S)


def _wait(db: Database, job_id: int, until: Any, timeout: float = 30.0) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        with db.read() as conn:
            record = get_job(conn=conn, job_id=job_id)
        if until(record) or time.monotonic() > deadline:
            return record
        time.sleep(0.05)


def test_a_second_engine_leaves_a_live_holders_job_alone(store: tuple[str, Database], recorder: Recorder) -> None:
    url, db = store
    with db.write() as conn:
        job_id = create_job(conn=conn, upload_path="/up/a/x.bag", map_name="a", options={"attempts": 0}).id
    first, second = _engine(url, db), _engine(url, db)
    first.start()
    _wait(db, job_id, lambda r: r.progress > 0)
    second.start()  # a second server on the same database, started by mistake (or a replica)
    record = _wait(db, job_id, lambda r: r.status == "done")
    first.stop()
    second.stop()
    assert second.recovered == ([], [])  # its start took nothing over
    assert (record.status, record.progress, record.lease_token, record.options) == ("done", 1.0, 1, {"attempts": 0})
    assert recorder.runs == [(1, "finished")]  # one run, by the first engine, not interrupted
    assert recorder.finishes == [(1, True)]  # finished once; the second engine wrote no outcome


def test_a_stale_holder_is_fenced_off_and_stops(store: tuple[str, Database], recorder: Recorder) -> None:
    url, db = store
    with db.write() as conn:
        job_id = create_job(conn=conn, upload_path="/up/a/x.bag", map_name="a", options={"attempts": 0}).id
    stale, second = _engine(url, db), _engine(url, db)
    stale._lease_loop = lambda: None  # type: ignore[method-assign]  # a stalled server: no lease renewals
    stale.start()
    _wait(db, job_id, lambda r: r.progress > 0)
    second.start()  # takes the job over once the stale holder's lease has lapsed (at start or within a lease)
    record = _wait(db, job_id, lambda r: r.status == "done")
    stale.stop()
    second.stop()
    # the stale holder's next progress write was refused: it stopped there and recorded nothing
    assert (1, "LeaseLost") in recorder.runs and (1, "finished") not in recorder.runs
    assert recorder.runs[-1] == (3, "finished")  # taken over (token 2) and claimed (token 3) by the second
    assert recorder.finishes == [(3, True)]  # finished once, by the holder of the current token
    assert (record.status, record.progress, record.lease_token) == ("done", 1.0, 3)
    assert record.options == {"attempts": 1}


def test_a_second_sqlite_server_is_refused_until_the_first_is_gone(make_api: Any) -> None:
    first: Api = make_api()
    second = TestClient(create_app(first.settings))
    with pytest.raises(ConflictError) as refused:
        second.__enter__()
    message = str(refused.value)
    assert "\n" not in message and f"pid {os.getpid()}" in message and "server-lock" in message
    assert first.client.get("/healthz").status_code == 200  # the first server is untouched
    first.client.__exit__(None, None, None)
    with TestClient(create_app(first.settings)) as third:  # the lock was released with the first server
        assert third.get("/healthz").status_code == 200


def test_the_lock_of_a_killed_process_is_taken_over(tmp_path: Path) -> None:
    lock = ServerLock(tmp_path / "map.db.server-lock")
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from pathlib import Path; from mapserver.api.lifecycle import "
         "ServerLock; ServerLock(Path(sys.argv[1])).acquire(); print('held', flush=True); time.sleep(60)",
         str(lock.path)],
        stdout=subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[3])},
    )  # fmt: skip
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == b"held"
        with pytest.raises(ConflictError, match=f"pid {holder.pid} on"):
            lock.acquire()
        holder.send_signal(signal.SIGKILL)
        holder.wait(10)
        lock.acquire()  # the kernel dropped the dead process's lock: no cleanup needed
        assert lock.held and f"pid {os.getpid()}" in lock.path.read_text()
    finally:
        holder.kill()
        holder.wait(10)
        lock.release()
    assert lock.path.read_text() == ""  # released: the file stays, naming nobody


def test_a_taken_port_is_refused_before_any_job_is_touched(store: tuple[str, Database], tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:  # fmt: skip
    """The measured fault: a second server recovered the first's running job, then found its port taken."""
    from mapserver.cli import main

    url, db = store
    with db.write() as conn:
        job_id = create_job(conn=conn, upload_path="/up/a/x.bag", map_name="a", options={"attempts": 0}).id
        claim_next_job(conn=conn, owner="first", lease_s=None)  # running, no lease: recovery would take it
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code = main(["serve", "--db", url, "--port", str(port), "--upload-dir", str(tmp_path / "uploads")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and err == [f"ERROR: cannot listen on 127.0.0.1:{port}: Address already in use "
                                 "(another server on this port? see --port)"]  # fmt: skip
    with db.read() as conn:
        record = get_job(conn=conn, job_id=job_id)
    assert (record.status, record.lease_token, record.options) == ("running", 1, {"attempts": 0})  # untouched
    lock = ServerLock.for_settings(Settings(db_url=url))
    if lock is not None:  # SQLite: the refused server let go of the database's lock
        lock.acquire()
        lock.release()

"""Real ``mapserver serve`` processes (issue 61, items 5 and 6): a second server, kill -9 and restart.

* A second server on the same SQLite database is refused at start with one line and writes nothing to
  the first server's running job, which finishes once; after the first server is killed, a new one takes
  its lock over and recovers the job it left running.
* A server killed (kill -9) in the middle of receiving one upload and unpacking another leaves a ``.part``
  file and a half-unpacked folder; the next start removes both and keeps the files of the jobs still
  queued, which then run.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from mapserver.store import open_database
from mapserver.store.jobs import JobRecord, get_job
from tests.mapserver.api.conftest import MAPSERVER, Server, bearer, free_port, make_token, wait_job
from tests.mapserver.api.logs import write_strip_log

pytestmark = pytest.mark.slow

SLOW_UNPACK = """\
import sys, time, zipfile
read = zipfile.ZipExtFile.read
def slow(self, n=-1):
    time.sleep(0.1)
    return read(self, n)
zipfile.ZipExtFile.read = slow
from mapserver.cli import main
sys.exit(main(sys.argv[1:]))
"""
"""``mapserver serve`` whose zip reads take 0.1 s per MiB: unpacking is slow enough to be killed midway."""


def _upload(url: str, token: str, path: Path, **fields: str) -> int:
    with path.open("rb") as handle:
        response = httpx.post(f"{url}/v1/sessions", files={"file": (path.name, handle)}, data=fields,
                              headers=bearer(token), timeout=120)  # fmt: skip
    assert response.status_code == 202, response.text
    return int(response.json()["job"])


def _job(db_url: str, job_id: int) -> JobRecord:
    with open_database(db_url) as db, db.read() as conn:
        return get_job(conn=conn, job_id=job_id)


def _running(server: Server, token: str, job_id: int, *, timeout: float = 120.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    state: dict[str, Any] = {}
    while time.monotonic() < deadline:
        state = httpx.get(f"{server.url}/v1/jobs/{job_id}", headers=bearer(token)).json()
        if state["status"] == "running" and state["progress"] > 0.02:
            return state
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} did not run: {state}")


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Server]:
    srv = Server(f"sqlite:///{tmp_path / 'served.db'}", tmp_path / "uploads", free_port(), tmp_path / "server.log")
    try:
        yield srv
    finally:
        srv.stop()


def test_a_second_server_is_refused_and_a_new_one_recovers_after_a_kill(served: Server, tmp_path: Path) -> None:
    served.start()
    assert served.process is not None
    token = make_token(served.db_url, "write")
    first = _upload(served.url, token, write_strip_log(tmp_path / "logs" / "first.bag", laps=80.0),
                    preset="irat", map="first")  # fmt: skip
    before = _running(served, token, first)
    started = time.monotonic()
    second = subprocess.run(
        [MAPSERVER, "serve", "--db", served.db_url, "--port", str(free_port()), "--upload-dir",
         str(served.upload_dir), "--log-level", "warning"],
        capture_output=True, timeout=120, check=False,
    )  # fmt: skip
    refused_s = time.monotonic() - started
    lines = second.stderr.decode().strip().splitlines()
    assert second.returncode == 1 and second.stdout == b"", second
    assert len(lines) == 1 and lines[0].startswith(f"ERROR: another mapserver server (pid {served.process.pid} "), lines
    record = _job(served.db_url, first)  # untouched by the second server: still the first claim, no takeover
    assert record.status in ("running", "done") and record.lease_token == 1
    assert (record.options or {}).get("attempts") == 0
    when_refused = (record.status, record.progress)
    with httpx.Client(base_url=served.url) as client:
        done = wait_job(client, first, bearer(token), timeout=300)
    assert done["status"] == "done", done
    record = _job(served.db_url, first)
    assert (record.lease_token, (record.options or {}).get("attempts")) == (1, 0)  # finished once, by the first
    print(f"second server refused after {refused_s:.1f} s; the job was at {before['progress']:.2f} when it started "
          f"and {when_refused} when it was refused")

    # pair: the first server killed in the middle of a job; the next one takes the lock over and recovers it
    other_log = write_strip_log(tmp_path / "logs" / "again.bag", laps=40.0, seed=11, t0_ns=1_800_000_000_000_000_000)
    again = _upload(served.url, token, other_log, preset="irat", map="again")
    _running(served, token, again)
    served.kill()
    assert _job(served.db_url, again).status == "running"
    served.start()
    with httpx.Client(base_url=served.url) as client:
        done = wait_job(client, again, bearer(token), timeout=300)
    assert done["status"] == "done", done
    record = _job(served.db_url, again)
    assert (record.lease_token, (record.options or {}).get("attempts")) == (3, 1)  # recovered (2), claimed (3)


def _stream_upload(url: str, token: str, stop: threading.Event) -> None:
    """Send a multipart upload slowly (chunked, 256 KiB every 0.1 s) until ``stop`` or the server dies."""
    boundary = "lifecycle-boundary"

    def body() -> Iterator[bytes]:
        yield (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"slow.bag\"\r\n"
               "Content-Type: application/octet-stream\r\n\r\n").encode()  # fmt: skip
        while not stop.is_set():
            yield os.urandom(256 << 10)
            time.sleep(0.1)

    headers = {**bearer(token), "Content-Type": f"multipart/form-data; boundary={boundary}"}
    with contextlib.suppress(httpx.HTTPError):  # the server is killed mid-upload
        httpx.post(f"{url}/v1/sessions", content=body(), headers=headers, timeout=120)


def _big_zip(path: Path, size: int) -> Path:
    """A zip holding one stored (uncompressed) entry of ``size`` random bytes: unpacking writes ``size`` bytes."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
        zf.writestr("mission/big.bag", os.urandom(size))
    return path


def _leftovers(root: Path, jobs: set[Path]) -> tuple[list[Path], list[Path], int]:
    parts = sorted((root / ".incoming").glob("*.part"))
    folders = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".") and p not in jobs)
    size = sum(f.stat().st_size for p in [*parts, *folders] for f in ([p] if p.is_file() else p.rglob("*"))
               if f.is_file())  # fmt: skip
    return parts, folders, size


def test_kill_9_while_receiving_and_unpacking_then_restart(tmp_path: Path) -> None:
    db_url, root, port = f"sqlite:///{tmp_path / 'served.db'}", tmp_path / "uploads", free_port()
    log = (tmp_path / "slow-server.log").open("ab")
    slow = subprocess.Popen([sys.executable, "-c", SLOW_UNPACK, "serve", "--db", db_url, "--port", str(port),
                             "--upload-dir", str(root), "--workers", "1", "--log-level", "warning"],
                            stdout=log, stderr=subprocess.STDOUT)  # fmt: skip
    restarted = Server(db_url, root, port, tmp_path / "server.log")
    stop = threading.Event()
    try:
        restarted.process = slow
        _wait_healthy(restarted)
        token = make_token(db_url, "write")
        running = _upload(restarted.url, token, write_strip_log(tmp_path / "logs" / "long.bag", laps=80.0),
                          preset="irat", map="long")  # fmt: skip
        queued = _upload(restarted.url, token, write_strip_log(tmp_path / "logs" / "short.bag"), preset="irat",
                         map="short")  # the server's one worker is busy: it waits  # fmt: skip
        _running(restarted, token, running)
        job_folders = {Path(_job(db_url, j).upload_path).parent for j in (running, queued)}
        big = _big_zip(tmp_path / "mission.zip", 40 << 20)
        threads = [threading.Thread(target=_stream_upload, args=(restarted.url, token, stop)),
                   threading.Thread(target=lambda: _post_quietly(restarted.url, token, big))]  # fmt: skip
        for thread in threads:
            thread.start()
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            parts, folders, _size = _leftovers(root, job_folders)
            unpacked = sum(f.stat().st_size for d in folders for f in d.rglob("*") if f.is_file())
            if len(parts) >= 2 and 2 << 20 < unpacked < 40 << 20 and parts[0].stat().st_size > 0:
                break
            time.sleep(0.05)
        slow.send_signal(signal.SIGKILL)  # in the middle of receiving one upload and unpacking another
        slow.wait(10)
        stop.set()
        for thread in threads:
            thread.join(30)
        parts, folders, size = _leftovers(root, job_folders)
        assert len(parts) >= 2 and len(folders) == 1, (parts, folders)
        assert _job(db_url, running).status == "running" and _job(db_url, queued).status == "queued"

        restarted.process = None
        started = time.monotonic()
        restarted.start()
        restart_s = time.monotonic() - started
        assert _leftovers(root, job_folders)[:2] == ([], [])  # the .part files and the half-unpacked folder
        for job_id in (running, queued):  # the jobs' own files stay (the queued one has not run yet)
            assert Path(_job(db_url, job_id).upload_path).is_file()
        with httpx.Client(base_url=restarted.url) as client:
            outcomes = [wait_job(client, j, bearer(token), timeout=300) for j in (running, queued)]
        assert [o["status"] for o in outcomes] == ["done", "done"], outcomes
        print(f"kill -9 left {len(parts)} .part files and {len(folders)} half-unpacked folder, {size} bytes; "
              f"removed by the restart ({restart_s:.1f} s to healthy)")
    finally:
        stop.set()
        if slow.poll() is None:
            slow.kill()
            slow.wait(10)
        restarted.stop()
        log.close()


def _post_quietly(url: str, token: str, path: Path) -> None:
    with contextlib.suppress(httpx.HTTPError), path.open("rb") as handle:  # the server is killed while unpacking
        httpx.post(f"{url}/v1/sessions", files={"file": (path.name, handle)}, headers=bearer(token), timeout=120)


def _wait_healthy(server: Server, timeout: float = 60.0) -> None:
    assert server.process is not None
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if server.process.poll() is not None:
            raise AssertionError("the server exited")
        try:
            if httpx.get(server.url + "/healthz", timeout=1.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.1)
    raise AssertionError("the server did not start")

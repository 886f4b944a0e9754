"""A local cluster for the Celery engine tests: a PostgreSQL schema, a Redis queue, worker and API processes.

Every test gets its own schema and queue name (and worker names), so parallel test runs never share
jobs or messages; every process is started in its own session and its whole process group is
killed at teardown (SIGTERM, then SIGKILL), whatever the test did.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.mapserver.api.conftest import MAPSERVER, bearer, free_port, make_token
from tests.mapserver.store.conftest import _pg_drop, _pg_schema_url, pg_unreachable

REDIS = os.environ.get("MAPSERVER_TEST_REDIS", "redis://127.0.0.1:6379/0")
RABBITMQ = os.environ.get("MAPSERVER_TEST_RABBITMQ", "amqp://guest:guest@127.0.0.1:5672//")
LEASE_S = 2.0


@cache
def broker_unreachable(url: str) -> str | None:
    """Return why the broker cannot be used, or None when it can."""
    from kombu import Connection

    try:
        with Connection(url, connect_timeout=2) as conn:
            conn.ensure_connection(max_retries=1)
    except Exception as err:  # any client or network failure means "unreachable"
        return f"broker unreachable at {url}: {err}"
    return None


@dataclass
class Cluster:
    """Processes of one test: workers and API servers on one schema, one queue, one upload directory."""

    db_url: str
    queue: str
    tmp: Path
    broker: str = REDIS
    processes: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)
    ports: dict[str, int] = field(default_factory=dict)
    token: str = ""

    @property
    def uploads(self) -> Path:
        return self.tmp / "shared-uploads"

    def _spawn(self, name: str, args: list[str]) -> subprocess.Popen[bytes]:
        log = (self.tmp / f"{name}.log").open("ab")
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        process = subprocess.Popen([MAPSERVER, *args], stdout=log, stderr=subprocess.STDOUT, env=env,
                                   start_new_session=True)  # fmt: skip
        self.processes[name] = process
        return process

    def worker_name(self, name: str) -> str:
        return f"{name}-{self.queue}@test"

    def start_worker(self, name: str, concurrency: int = 1) -> None:
        """Start ``mapserver worker`` (returns at once; :meth:`wait_workers` waits for it)."""
        self._spawn(name, ["worker", "--db", self.db_url, "--broker", self.broker, "--queue", self.queue,
                           "--name", self.worker_name(name), "--concurrency", str(concurrency),
                           "--lease-seconds", str(LEASE_S), "--log-level", "info"])  # fmt: skip

    def start_api(self, name: str) -> None:
        """Start ``mapserver serve --jobs celery`` on a free port (or the port it had before)."""
        port = self.ports.setdefault(name, free_port())
        self._spawn(name, ["serve", "--db", self.db_url, "--jobs", "celery", "--broker", self.broker,
                           "--queue", self.queue, "--lease-seconds", str(LEASE_S), "--port", str(port),
                           "--upload-dir", str(self.uploads), "--log-level", "warning"])  # fmt: skip

    def url(self, name: str) -> str:
        return f"http://127.0.0.1:{self.ports[name]}"

    def wait_api(self, name: str, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self._check_alive(name)
            try:
                if httpx.get(self.url(name) + "/healthz", timeout=5.0).status_code == 200:
                    if not self.token:
                        self.token = make_token(self.db_url, "write")
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        raise AssertionError(f"{name} did not start: {self.log(name)}")

    def wait_workers(self, api: str, names: list[str], timeout: float = 60.0) -> dict[str, Any]:
        """Wait until ``/healthz`` of ``api`` lists the named workers; return that answer."""
        wanted = {self.worker_name(n) for n in names}
        deadline = time.monotonic() + timeout
        health: dict[str, Any] = {}
        while time.monotonic() < deadline:
            for name in names:
                self._check_alive(name)
            health = httpx.get(self.url(api) + "/healthz", timeout=10.0).json()
            if wanted <= set(health.get("workers") or []):
                return health
            time.sleep(0.5)
        raise AssertionError(f"workers not seen: {health}")

    def _check_alive(self, name: str) -> None:
        if self.processes[name].poll() is not None:
            raise AssertionError(f"{name} exited: {self.log(name)}")

    def log(self, name: str) -> str:
        return (self.tmp / f"{name}.log").read_text(errors="replace")[-3000:]

    def upload(self, api: str, path: Path, **fields: str) -> dict[str, Any]:
        with path.open("rb") as handle:
            response = httpx.post(f"{self.url(api)}/v1/sessions", files={"file": (path.name, handle)}, data=fields,
                                  headers=bearer(self.token), timeout=60)  # fmt: skip
        assert response.status_code == 202, response.text
        return response.json()

    def job(self, api: str, job: int) -> dict[str, Any]:
        return httpx.get(f"{self.url(api)}/v1/jobs/{job}", headers=bearer(self.token), timeout=10).json()

    def wait_jobs(self, api: str, jobs: list[int], timeout: float = 90.0) -> list[dict[str, Any]]:
        deadline = time.monotonic() + timeout
        while True:
            states = [self.job(api, j) for j in jobs]
            if all(s["status"] in ("done", "failed") for s in states) or time.monotonic() > deadline:
                return states
            time.sleep(0.2)

    def get(self, api: str, path: str) -> Any:
        return httpx.get(self.url(api) + path, headers=bearer(self.token), timeout=30).json()

    def signal(self, name: str, sig: int) -> None:
        """Send ``sig`` to the process group of ``name`` and wait for the process."""
        process = self.processes[name]
        if process.poll() is None:
            os.killpg(process.pid, sig)
        try:
            process.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait(10)

    def close(self) -> None:
        for process in self.processes.values():
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGTERM)
        for process in self.processes.values():
            try:
                process.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait(10)
        for process in self.processes.values():  # a pool child may outlive its parent
            with contextlib.suppress(ProcessLookupError):
                os.killpg(process.pid, signal.SIGKILL)


@contextlib.contextmanager
def local_cluster(tmp_path: Path, broker: str = REDIS) -> Iterator[Cluster]:
    """A fresh PostgreSQL schema and broker queue; the processes started on it are killed at the end."""
    reason = pg_unreachable() or broker_unreachable(broker)
    if reason is not None:
        pytest.skip(reason)
    url, schema = _pg_schema_url()
    queue = f"mapserver-test-{uuid.uuid4().hex[:10]}"
    made = Cluster(url, queue, tmp_path, broker)
    try:
        yield made
    finally:
        made.close()
        _pg_drop(schema)
        _delete_queue(broker, queue)


def _delete_queue(broker: str, queue: str) -> None:
    from kombu import Connection

    with contextlib.suppress(Exception), Connection(broker, connect_timeout=2) as conn:
        conn.default_channel.queue_delete(queue)

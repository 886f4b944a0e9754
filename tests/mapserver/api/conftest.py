"""API test fixtures: an app on a SQLite file in tmp_path, tokens, upload helpers, a real server process."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

from mapserver.api import Settings, create_app
from mapserver.store import open_database
from mapserver.store.tokens import create_token
from tests.mapserver.api.logs import write_strip_log

MAPSERVER = str(Path(sys.executable).with_name("mapserver"))


def make_token(db_url: str, scope: str) -> str:
    with open_database(db_url) as db, db.write() as conn:
        token, _record = create_token(conn=conn, scope=scope)
    return token


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@dataclass
class Api:
    """A TestClient with the database URL and a write and a read token."""

    client: TestClient
    db_url: str
    settings: Settings
    write: dict[str, str]
    read: dict[str, str]

    def upload(self, path: Path, *, name: str | None = None, headers: dict[str, str] | None = None,
               **fields: str) -> httpx.Response:  # fmt: skip
        with path.open("rb") as handle:
            return self.client.post(
                "/v1/sessions",
                files={"file": (name or path.name, handle, "application/octet-stream")},
                data=fields,
                headers=self.write if headers is None else headers,
            )

    def wait(self, job: int, timeout: float = 60.0) -> dict[str, Any]:
        return wait_job(self.client, job, self.read, timeout)


def wait_job(client: Any, job: int, headers: dict[str, str], timeout: float = 60.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        body = client.get(f"/v1/jobs/{job}", headers=headers).json()
        if body["status"] in ("done", "failed") or time.monotonic() > deadline:
            return body
        time.sleep(0.05)


def api_settings(tmp_path: Path, **overrides: Any) -> Settings:
    values: dict[str, Any] = {
        "db_url": f"sqlite:///{tmp_path / 'api.db'}",
        "upload_dir": tmp_path / "uploads",
        "workers": 2,
        "progress_interval_s": 0.0,
    }
    values.update(overrides)
    return Settings(**values)


@pytest.fixture
def make_api(tmp_path: Path) -> Iterator[Any]:
    """Factory: ``make_api(**settings)`` → a started :class:`Api` (closed at teardown)."""
    opened: list[TestClient] = []

    def factory(**overrides: Any) -> Api:
        settings = api_settings(tmp_path, **overrides)
        client = TestClient(create_app(settings))
        client.__enter__()
        opened.append(client)
        return Api(client, settings.db_url, settings, bearer(make_token(settings.db_url, "write")),
                   bearer(make_token(settings.db_url, "read")))  # fmt: skip

    yield factory
    for client in opened:
        client.__exit__(None, None, None)


@pytest.fixture
def api(make_api: Any) -> Api:
    return make_api()


@pytest.fixture
def strip_log(tmp_path: Path) -> Path:
    return write_strip_log(tmp_path / "logs" / "strip.bag")


# ------------------------------------------------------------------------------------------ real server
def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@dataclass
class Server:
    """A ``mapserver serve`` process on a free loopback port."""

    db_url: str
    upload_dir: Path
    port: int
    log: Path
    process: subprocess.Popen[bytes] | None = None
    extra: tuple[str, ...] = ()  # more ``serve`` flags

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, timeout: float = 60.0) -> None:
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        handle = self.log.open("ab")
        self.process = subprocess.Popen(
            [MAPSERVER, "serve", "--db", self.db_url, "--host", "127.0.0.1", "--port", str(self.port),
             "--upload-dir", str(self.upload_dir), "--workers", "2", "--log-level", "warning", *self.extra],
            stdout=handle, stderr=subprocess.STDOUT, env=env,
        )  # fmt: skip
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise AssertionError(f"server exited: {self.log.read_text()[-2000:]}")
            try:
                if httpx.get(self.url + "/healthz", timeout=1.0).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        raise AssertionError(f"server did not start: {self.log.read_text()[-2000:]}")

    def kill(self) -> None:
        assert self.process is not None
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(10)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(10)


@pytest.fixture
def server(tmp_path: Path) -> Iterator[Server]:
    db_url = f"sqlite:///{tmp_path / 'served.db'}"
    srv = Server(db_url, tmp_path / "served-uploads", free_port(), tmp_path / "server.log")
    try:
        yield srv
    finally:
        srv.stop()

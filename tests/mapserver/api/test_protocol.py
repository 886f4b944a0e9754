"""HTTP edges of uploads on a real ``serve`` process: the body after the closing boundary, idle uploads.

Pairs: a body that goes on after its closing boundary is refused with 400 long before its declared 3 GB
arrive, while one that ends with a short epilogue is accepted; an upload that pauses longer than
``--read-timeout`` gets 408 and its connection closed, while one that pauses less is accepted.
"""

from __future__ import annotations

import select
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.mapserver.api.conftest import MAPSERVER, Server, make_token
from tests.mapserver.api.logs import write_strip_log

BOUNDARY = "mapserver-test-boundary"


@pytest.fixture
def served(server: Server) -> Iterator[tuple[Server, str]]:
    """The server fixture started with ``--read-timeout 1``; yields it and a write token."""
    token = make_token(server.db_url, "write")
    server.process = subprocess.Popen(
        [MAPSERVER, "serve", "--db", server.db_url, "--port", str(server.port), "--upload-dir", str(server.upload_dir),
         "--read-timeout", "1", "--log-level", "warning"],
        stdout=server.log.open("ab"), stderr=subprocess.STDOUT,
    )  # fmt: skip
    deadline = time.monotonic() + 60
    while True:
        try:
            if httpx.get(server.url + "/healthz", timeout=1).status_code == 200:
                break
        except httpx.HTTPError:
            assert time.monotonic() < deadline, server.log.read_text()[-2000:]
            time.sleep(0.1)
    yield server, token


def _head(token: str, length: int) -> bytes:
    return (
        f"POST /v1/sessions HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {token}\r\n"
        f"Content-Type: multipart/form-data; boundary={BOUNDARY}\r\nContent-Length: {length}\r\n\r\n"
    ).encode()


def _parts(log: Path) -> tuple[bytes, bytes]:
    """Return the body up to the file's bytes, and the rest up to and with the closing boundary."""
    opening = (
        f"--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"preset\"\r\n\r\nirat\r\n"
        f"--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"{log.name}\"\r\n"
        "Content-Type: application/octet-stream\r\n\r\n"
    ).encode()
    return opening + log.read_bytes(), f"\r\n--{BOUNDARY}--\r\n".encode()


def _response(sock: socket.socket, timeout: float) -> bytes:
    sock.settimeout(timeout)
    data = b""
    try:
        while b"\r\n\r\n" not in data or not data.rstrip().endswith(b"}"):
            piece = sock.recv(65536)
            if not piece:
                break
            data += piece
    except (TimeoutError, ConnectionResetError):
        pass
    return data


def test_a_body_past_its_closing_boundary_is_refused_early(served: tuple[Server, str], tmp_path: Path) -> None:
    server, token = served
    log = write_strip_log(tmp_path / "trail.bag", laps=0.5)
    body, closing = _parts(log)
    declared = 3_000_000_000
    sent = 0
    started = time.monotonic()
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        sock.sendall(_head(token, declared) + body + closing)
        junk = b"x" * 65536
        try:
            while sent < 500 * (1 << 20) and not select.select([sock], [], [], 0)[0]:
                sock.sendall(junk)
                sent += len(junk)
        except (BrokenPipeError, ConnectionResetError):
            pass
        answer = _response(sock, 10)
    seconds = time.monotonic() - started
    assert answer.startswith(b"HTTP/1.1 400"), answer[:300]
    assert b"after the multipart closing boundary" in answer
    assert sent < 64 * (1 << 20) and seconds < 10, (sent, seconds)  # of a declared 3 GB
    # the pair: the same upload ending with a short epilogue is accepted
    epilogue = b"\r\n"
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        sock.sendall(_head(token, len(body) + len(closing) + len(epilogue)) + body + closing + epilogue)
        accepted = _response(sock, 30)
    assert accepted.startswith(b"HTTP/1.1 202"), accepted[:300]


def test_an_idle_upload_gets_408_and_a_slow_one_is_accepted(served: tuple[Server, str], tmp_path: Path) -> None:
    server, token = served
    log = write_strip_log(tmp_path / "idle.bag", laps=0.5)
    body, closing = _parts(log)
    started = time.monotonic()
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        sock.sendall(_head(token, len(body) + len(closing)) + body[: len(body) // 2])
        answer = _response(sock, 15)
        waited = time.monotonic() - started
        sock.settimeout(5)
        closed = sock.recv(1) == b""  # the server closed the connection
    assert answer.startswith(b"HTTP/1.1 408"), answer[:300]
    assert b"sent nothing for 1 s" in answer and b"connection: close" in answer.lower()
    assert 0.9 < waited < 10 and closed
    with socket.create_connection(("127.0.0.1", server.port)) as sock:
        sock.sendall(_head(token, len(body) + len(closing)))
        step = len(body) // 3 + 1
        for k in range(0, len(body), step):
            sock.sendall(body[k : k + step])
            time.sleep(0.4)  # pauses shorter than the timeout
        sock.sendall(closing)
        accepted = _response(sock, 30)
    assert accepted.startswith(b"HTTP/1.1 202"), accepted[:300]

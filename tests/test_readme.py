"""The README's shell examples run as written, in the order they appear (issue 62).

Every fenced ``sh``/``bash`` block of README.md is run with ``bash -eu`` in one fresh directory, each block
in its own shell (files carry over from block to block, shell variables do not), with ``mapserver`` on
``PATH``: a shim that runs this checkout's ``mapserver.cli`` with the interpreter running the tests (the
virtual environment's, whose ``mapserver`` is the same code after ``make install``). Each block must exit 0.

A block is marked by an HTML comment on the line before its fence:

* ``<!-- readme-test: skip (reason) -->`` — not run (``make run`` serves forever; PostgreSQL, a broker or
  another tool's files are needed);
* ``<!-- readme-test: background (reason) -->`` — started and left running (the ``serve`` example) until
  the last block has run; the blocks after it talk to it. Its port, 8000 in the README, is replaced by a
  free one in every block, so the test never meets another server.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MARKER = re.compile(r"<!--\s*readme-test:\s*(\w+)\b.*-->")
KINDS = ("run", "skip", "background")
BLOCK_TIMEOUT_S = 300
SERVER_START_S = 60


@dataclass(frozen=True)
class Block:
    """One fenced shell block: its first line in the README, how the test treats it, and its text."""

    line: int
    kind: str
    code: str


def shell_blocks(text: str) -> list[Block]:
    """Return the ``sh``/``bash`` blocks of a Markdown text in order, with the marker before each fence."""
    lines = text.splitlines()
    blocks: list[Block] = []
    i = 0
    while i < len(lines):
        fence = lines[i].strip()
        if fence.startswith("```") and fence[3:].strip() in ("sh", "bash", "shell", "console"):
            previous = next((lines[j] for j in range(i - 1, -1, -1) if lines[j].strip()), "")
            marker = MARKER.search(previous)
            kind = marker.group(1) if marker else "run"
            end = next(j for j in range(i + 1, len(lines)) if lines[j].strip().startswith("```"))
            blocks.append(Block(line=i + 1, kind=kind, code="\n".join(lines[i + 1 : end]) + "\n"))
            i = end
        i += 1
    return blocks


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _shim(directory: Path) -> None:
    """Write a ``mapserver`` command running this checkout's CLI with this interpreter."""
    directory.mkdir()
    shim = directory / "mapserver"
    code = "import sys; from mapserver.cli import entry; sys.argv[0] = 'mapserver'; sys.exit(entry())"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -c "{code}" "$@"\n')
    shim.chmod(0o755)


def _wait_for_server(server: subprocess.Popen[bytes], port: int, log: Path) -> None:
    deadline = time.monotonic() + SERVER_START_S
    while time.monotonic() < deadline:
        if server.poll() is not None:
            pytest.fail(f"the README's server exited with {server.returncode}:\n{log.read_text()[-4000:]}")
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=2) as answer:
                if answer.status == 200:
                    return
        except OSError:
            time.sleep(0.3)
    pytest.fail(f"the README's server did not answer within {SERVER_START_S} s:\n{log.read_text()[-4000:]}")


def _stop(server: subprocess.Popen[bytes]) -> None:
    if server.poll() is None:
        os.killpg(server.pid, signal.SIGTERM)
        try:
            server.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait()


def test_the_readme_blocks_are_parsed_with_their_markers() -> None:
    blocks = shell_blocks(README.read_text(encoding="utf-8"))
    assert {b.kind for b in blocks} <= set(KINDS), [(b.line, b.kind) for b in blocks if b.kind not in KINDS]
    assert sum(b.kind == "run" for b in blocks) >= 10
    assert [b.kind for b in blocks].count("background") == 1
    sample = "<!-- readme-test: skip (x) -->\n```sh\nmake run\n```\n\n```bash\nls\n```\n```yaml\na: 1\n```\n"
    assert shell_blocks(sample) == [Block(2, "skip", "make run\n"), Block(6, "run", "ls\n")]


def test_the_readmes_shell_examples_run_in_order(tmp_path: Path) -> None:
    if shutil.which("curl") is None:
        pytest.skip("the README's REST examples need curl")
    port = _free_port()
    _shim(tmp_path / "bin")
    env = {
        **os.environ,
        "PATH": os.pathsep.join([str(tmp_path / "bin"), str(ROOT / ".venv" / "bin"), os.environ.get("PATH", "")]),
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    env.pop("MAPSERVER_DB", None)  # the examples name their databases
    work = tmp_path / "tour"
    work.mkdir()
    server: subprocess.Popen[bytes] | None = None
    log = tmp_path / "server.log"
    try:
        for block in shell_blocks(README.read_text(encoding="utf-8")):
            code = block.code.replace("localhost:8000", f"localhost:{port}").replace("--port 8000", f"--port {port}")
            if block.kind == "skip":
                continue
            if block.kind == "background":
                assert server is None, f"README.md:{block.line}: a second background block"
                with log.open("wb") as sink:
                    argv = ["bash", "-eu", "-c", "exec " + code.strip()]
                    server = subprocess.Popen(argv, cwd=work, env=env, stdout=sink, stderr=subprocess.STDOUT,
                                              start_new_session=True)  # fmt: skip
                _wait_for_server(server, port, log)
                continue
            done = subprocess.run(["bash", "-eu", "-c", code], cwd=work, env=env, capture_output=True, text=True,
                                  timeout=BLOCK_TIMEOUT_S, check=False)  # fmt: skip
            assert done.returncode == 0, (
                f"README.md:{block.line}: exit {done.returncode}\n{code}\n--- stdout\n{done.stdout[-3000:]}"
                f"\n--- stderr\n{done.stderr[-3000:]}"
            )
    finally:
        if server is not None:
            _stop(server)

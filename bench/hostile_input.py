"""Hostile uploads against a real ``mapserver serve``: bytes written, peak RSS, time and the answer per bomb.

Usage: python bench/hostile_input.py [--zeros-gib 2] [--out DIR] [--keep]

Builds, in DIR (default a temporary folder; bombs are reused when present):

* ``zeros.tar.bz2``, ``zeros.tar.gz``: a ROS 2 bag directory (``metadata.yaml`` and a ``--zeros-gib`` GiB file
  of zeros) as a tar, compressed as one stream (2 GiB: ~1.6 KB of bzip2, ~2 MB of gzip);
* ``zeros.zip``: the same file deflated (one stream, zip64);
* ``entries.zip``: 100,000 empty entries;
* ``png.bag``, ``jpeg.bag``: three 20000×20000 grey frames (valid PNG / JPEG payloads) and odometry;
* ``ordinary.tar.gz``, ``ordinary.zip``, ``ordinary.bag``: the API tests' strip log (the pair: accepted and
  processed).

Each upload goes to a fresh server (SQLite, default limits) so that ``VmHWM`` is that upload's peak; the
figures are the server process's ``/proc/PID/io`` ``wchar`` (bytes passed to write calls, files and sockets)
and ``write_bytes`` (bytes sent to the storage layer) over the request, ``VmHWM`` before and after, the
seconds to the answer, its status and body. Then ``mapserver process`` runs over each bag (peak RSS of the
child from ``wait4``). Last line: one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from mapserver.store import open_database  # noqa: E402
from mapserver.store.tokens import create_token  # noqa: E402
from tests.mapserver.api.logs import write_strip_log, zip_directory  # noqa: E402
from tests.mapserver.hostile import entries_zip, payload_bag, png_bomb, zeros_tar, zeros_zip  # noqa: E402


def jpeg_payload(width: int, height: int) -> bytes:
    """Return a valid grey JPEG of zeros of that size (encoded whole: 400 MB in this process for 20000²)."""
    ok, data = cv2.imencode(".jpg", np.zeros((height, width), np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 50])
    assert ok
    return data.tobytes()


def ordinary(out: Path) -> tuple[Path, Path, Path]:
    """Return the API tests' strip log as a ROS 2 bag directory in a .tar.gz and a .zip, and as a .bag."""
    bag = write_strip_log(out / "ordinary" / "rosbag2_ordinary", fmt="db3", directory=True)
    tgz = out / "ordinary.tar.gz"
    with tarfile.open(tgz, "w:gz") as tf:
        tf.add(bag, arcname=bag.name)
    return tgz, zip_directory(bag, out / "ordinary.zip"), write_strip_log(out / "ordinary.bag")


def build(out: Path, zeros: int) -> dict[str, Path]:
    out.mkdir(parents=True, exist_ok=True)
    files = {name: out / name for name in ("zeros.tar.bz2", "zeros.tar.gz", "zeros.zip", "entries.zip",
                                           "png.bag", "jpeg.bag")}  # fmt: skip
    makers = {
        "zeros.tar.bz2": lambda p: zeros_tar(p, zeros, "bz2", one_stream=True),
        "zeros.tar.gz": lambda p: zeros_tar(p, zeros, "gz", one_stream=True),
        "zeros.zip": lambda p: zeros_zip(p, zeros),
        "entries.zip": lambda p: entries_zip(p, 100_000),
        "png.bag": lambda p: payload_bag(p, [png_bomb(20000, 20000)] * 3, "png"),
        "jpeg.bag": lambda p: payload_bag(p, [jpeg_payload(20000, 20000)] * 3, "jpeg"),
    }
    for name, path in files.items():
        if not path.exists():
            started = time.perf_counter()
            makers[name](path)
            print(f"built {name}: {path.stat().st_size} bytes in {time.perf_counter() - started:.1f} s", flush=True)
    files["ordinary.tar.gz"], files["ordinary.zip"], files["ordinary.bag"] = ordinary(out)
    return files


def proc(pid: int) -> dict[str, int]:
    """Return ``wchar``, ``write_bytes`` and ``VmHWM`` (bytes) of a process."""
    from tests.mapserver.hostile import proc_figures

    return proc_figures(pid)


def free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def one_upload(work: Path, path: Path, wait_job: bool) -> dict[str, Any]:
    """Start a server, upload ``path``, measure, stop; return the figures."""
    db_url = f"sqlite:///{work / 'bench.db'}"
    with open_database(db_url) as db, db.write() as conn:
        token, _ = create_token(conn=conn, scope="write")
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    log = (work / "server.log").open("wb")
    server = subprocess.Popen(
        [sys.executable, "-c", "import sys; from mapserver.cli import entry; sys.argv[0] = 'mapserver'; entry()",
         "serve", "--db", db_url, "--port", str(port), "--upload-dir", str(work / "uploads"), "--log-level", "warning"],
        stdout=log, stderr=subprocess.STDOUT, env=env,
    )  # fmt: skip
    url = f"http://127.0.0.1:{port}"
    headers = {"Authorization": f"Bearer {token}"}
    try:
        for _ in range(300):
            try:
                if httpx.get(url + "/healthz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.1)
        before = proc(server.pid)
        started = time.perf_counter()
        with path.open("rb") as handle:
            response = httpx.post(url + "/v1/sessions", files={"file": (path.name, handle)}, data={"preset": "irat"},
                                  headers=headers, timeout=600)  # fmt: skip
        seconds = time.perf_counter() - started
        job = None
        if wait_job and response.status_code == 202:
            for _ in range(1200):
                job = httpx.get(f"{url}/v1/jobs/{response.json()['job']}", headers=headers).json()
                if job["status"] in ("done", "failed"):
                    break
                time.sleep(0.1)
        after = proc(server.pid)
    finally:
        server.terminate()
        server.wait(60)
        log.close()
    return {
        "upload": path.name, "upload_bytes": path.stat().st_size, "status": response.status_code,
        "body": response.json(), "seconds": round(seconds, 3),
        "wchar": after["wchar"] - before["wchar"], "write_bytes": after["write_bytes"] - before["write_bytes"],
        "rss_before": before["VmRSS"], "hwm_before": before["VmHWM"], "hwm_after": after["VmHWM"],
        "job": None if job is None else {k: job.get(k) for k in ("status", "error", "dropped")},
    }  # fmt: skip


def one_process(path: Path) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    started = time.perf_counter()
    child = subprocess.Popen(
        [sys.executable, "-c", "import sys; from mapserver.cli import entry; sys.argv[0] = 'mapserver'; entry()",
         "process", str(path), "--preset", "irat", "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
    )  # fmt: skip
    assert child.stdout is not None and child.stderr is not None
    stdout, stderr = child.stdout.read(), child.stderr.read()
    _pid, status, usage = os.wait4(child.pid, 0)
    return {
        "log": path.name, "exit": os.waitstatus_to_exitcode(status), "seconds": round(time.perf_counter() - started, 3),
        "peak_rss": usage.ru_maxrss * 1024, "stderr": stderr.decode().strip().splitlines()[-1:],
        "stdout": stdout.decode().strip().splitlines()[-1:],
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--zeros-gib", type=float, default=2.0)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="hostile-"))
    files = build(out, int(args.zeros_gib * (1 << 30)))
    results: dict[str, Any] = {"uploads": [], "process": []}
    for name, path in files.items():
        with tempfile.TemporaryDirectory(prefix="serve-", dir=out) as work:
            figures = one_upload(Path(work), path, wait_job=name.startswith("ordinary"))
        results["uploads"].append(figures)
        print(json.dumps(figures), flush=True)
    for name in ("png.bag", "jpeg.bag", "ordinary.bag"):
        figures = one_process(files[name])
        results["process"].append(figures)
        print(json.dumps(figures), flush=True)
    print(json.dumps(results))


if __name__ == "__main__":
    main()

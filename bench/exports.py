"""Heavy reads: the server's memory and /healthz latency while clients export a 100,000-experience map at once.

Usage: python bench/exports.py [--experiences 100000] [--clients 8] [--rounds 3] [--format json]
                               [--db-url URL] [--max-exports N]

1. Builds the city-block map of ``bench/api.py`` (``build_map``: the store's bulk writers, no frames
   processed) in a SQLite file in a temporary directory, or in an empty database given by ``--db-url``.
2. Starts a real ``mapserver serve`` process (anonymous reads; ``--max-exports`` passed on when given),
   reads its resident memory (``/proc/PID/status`` VmRSS) when idle, after one ``GET /v1/maps``.
3. ``--rounds`` times: ``--clients`` threads export the map at once (``GET /v1/maps/city/export``; bodies
   are read and counted, not kept) while one thread samples the server's VmRSS every 20 ms and another
   asks ``--probe`` (default ``/healthz``) every 20 ms; after each round it waits 3 s and reads VmRSS again.

Prints per round the peak RSS over idle, the RSS after the round, the exports' seconds and statuses, and
``/healthz`` p50/p99/max during the exports; the last line is one JSON object with every figure. Run it
against another checkout by putting that checkout first on ``PYTHONPATH`` (the server and the map
builder then come from it). Targets: peak ≤ 0.5 GB over idle, RSS back near idle after a round.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from api import build_map, free_port  # bench/api.py, beside this file

MAPSERVER = str(Path(sys.executable).with_name("mapserver"))
MIB = 1 << 20


def rss_bytes(pid: int, key: str = "VmRSS") -> int:
    """Return a memory figure of process ``pid`` from ``/proc/PID/status`` (kB there) in bytes."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
    raise SystemExit(f"no {key} for process {pid}")


def start_server(db_url: str, folder: Path, max_exports: int | None) -> tuple[subprocess.Popen[bytes], str]:
    """Start ``mapserver serve`` on a free port; return the process and its URL once /healthz answers."""
    port = free_port()
    command = [MAPSERVER, "serve", "--db", db_url, "--port", str(port), "--allow-anonymous-reads",
               "--upload-dir", str(folder / "uploads"), "--log-level", "warning"]  # fmt: skip
    if max_exports is not None:
        command += ["--max-exports", str(max_exports)]
    process = subprocess.Popen(command, stdout=(folder / "server.log").open("ab"), stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    for _ in range(600):
        try:
            if httpx.get(url + "/healthz", timeout=1).status_code == 200:
                return process, url
        except httpx.HTTPError:
            time.sleep(0.1)
    process.kill()
    raise SystemExit("server did not start: " + (folder / "server.log").read_text()[-2000:])


def idle_healthz(url: str, probes: int = 200) -> dict[str, float]:
    """Return /healthz latency percentiles (ms) with nothing else running: the reference for the rounds."""
    ms = []
    with httpx.Client(base_url=url, timeout=60) as http:
        for _ in range(probes):
            start = time.perf_counter()
            http.get("/healthz").raise_for_status()
            ms.append((time.perf_counter() - start) * 1000)
            time.sleep(0.005)
    return {"p50_ms": round(float(np.percentile(ms, 50)), 1), "p99_ms": round(float(np.percentile(ms, 99)), 1)}


def export_round(url: str, pid: int, clients: int, fmt: str, probe_path: str = "/healthz") -> dict[str, Any]:
    """Run ``clients`` concurrent exports; return their statuses, bytes, seconds, peak RSS and /healthz latency."""
    done = threading.Event()
    peak = [rss_bytes(pid)]
    health_ms: list[float] = []
    answers: list[tuple[int, int, float]] = []
    barrier = threading.Barrier(clients + 1)

    def sample() -> None:
        while not done.is_set():
            peak[0] = max(peak[0], rss_bytes(pid))
            time.sleep(0.02)

    def probe() -> None:
        with httpx.Client(base_url=url, timeout=60) as http:
            while not done.is_set():
                start = time.perf_counter()
                http.get(probe_path).raise_for_status()
                health_ms.append((time.perf_counter() - start) * 1000)
                time.sleep(0.02)

    def export() -> None:
        with httpx.Client(base_url=url, timeout=600) as http:
            barrier.wait()
            start = time.perf_counter()
            size = 0
            with http.stream("GET", "/v1/maps/city/export", params={"format": fmt}) as response:
                for chunk in response.iter_raw(1 << 16):
                    size += len(chunk)
            answers.append((response.status_code, size, time.perf_counter() - start))

    helpers = [threading.Thread(target=sample), threading.Thread(target=probe)]
    workers = [threading.Thread(target=export) for _ in range(clients)]
    for t in helpers + workers:
        t.start()
    barrier.wait()
    started = time.perf_counter()
    for t in workers:
        t.join()
    wall = time.perf_counter() - started
    done.set()
    for t in helpers:
        t.join()
    ms = np.asarray(health_ms or [float("nan")])
    return {
        "statuses": sorted(a[0] for a in answers), "bytes": max(a[1] for a in answers), "wall_s": round(wall, 2),
        "export_s_max": round(max(a[2] for a in answers), 2), "peak_rss": peak[0],
        "healthz_p50_ms": round(float(np.percentile(ms, 50)), 1),
        "healthz_p99_ms": round(float(np.percentile(ms, 99)), 1), "healthz_max_ms": round(float(ms.max()), 1),
        "healthz_probes": int(ms.size),
    }  # fmt: skip


def run(args: argparse.Namespace, folder: Path) -> dict[str, Any]:
    """Build the map, start the server, run the rounds; return the figures."""
    db_url = args.db_url or f"sqlite:///{folder / 'bench.db'}"
    start = time.perf_counter()
    links = build_map(db_url, args.experiences)
    print(f"stored map 'city': {args.experiences} experiences, {links} links in {time.perf_counter() - start:.1f} s")
    process, url = start_server(db_url, folder, args.max_exports)
    try:
        httpx.get(url + "/v1/maps", timeout=60).raise_for_status()
        time.sleep(1.0)
        idle = rss_bytes(process.pid)
        quiet = idle_healthz(url)
        print(f"server idle: {idle / MIB:.0f} MiB; /healthz alone p50 {quiet['p50_ms']} ms, p99 {quiet['p99_ms']} ms")
        rounds = []
        for k in range(args.rounds):
            figures = export_round(url, process.pid, args.clients, args.format, args.probe)
            time.sleep(3.0)
            figures["after_rss"] = rss_bytes(process.pid)
            figures["peak_over_idle_mib"] = round((figures["peak_rss"] - idle) / MIB, 1)
            figures["after_over_idle_mib"] = round((figures["after_rss"] - idle) / MIB, 1)
            rounds.append(figures)
            print(f"round {k + 1}: {args.clients} × {args.format} ({figures['bytes'] / MIB:.1f} MiB each) "
                  f"statuses {figures['statuses']}, {figures['wall_s']} s; peak RSS {figures['peak_rss'] / MIB:.0f} "
                  f"MiB (+{figures['peak_over_idle_mib']} over idle), after {figures['after_rss'] / MIB:.0f} MiB "
                  f"(+{figures['after_over_idle_mib']}); {args.probe} p50 {figures['healthz_p50_ms']} ms, p99 "
                  f"{figures['healthz_p99_ms']} ms, max {figures['healthz_max_ms']} ms")  # fmt: skip
        hwm = rss_bytes(process.pid, "VmHWM")
    finally:
        process.terminate()
        process.wait(60)
    return {"experiences": args.experiences, "links": links, "clients": args.clients, "format": args.format,
            "probe": args.probe,
            "max_exports": args.max_exports, "db": db_url.split(":", 1)[0], "idle_rss_mib": round(idle / MIB, 1),
            "idle_healthz": quiet,
            "vm_hwm_mib": round(hwm / MIB, 1), "load_average_1min": round(os.getloadavg()[0], 2),
            "rounds": rounds}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiences", type=int, default=100_000)
    parser.add_argument("--clients", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--format", default="json", choices=("json", "tum", "png", "g2o", "csv"))
    parser.add_argument("--db-url", help="an empty database (default: a SQLite file in a temporary directory)")
    parser.add_argument("--max-exports", type=int, help="passed to serve (absent: the server's default)")
    parser.add_argument("--probe", default="/healthz", help="the path timed during the exports (e.g. /v1/maps)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="mapserver-bench-exports-") as tmp:
        result = run(args, Path(tmp))
    print(json.dumps(result))


if __name__ == "__main__":
    main()

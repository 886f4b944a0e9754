"""Celery cluster throughput: 8 ``loop`` uploads over 4 maps with 1 and with 2 workers (issue 15).

Usage: python bench/cluster.py [--workers 1,2] [--rounds 1] [--broker URL] [--no-merge] [--keep-logs DIR] [--laps 2,1.5]

Simulates the ``loop`` scenario for 4 worlds (seeds 1-4), each with 2 laps and with 1.5 laps (``--laps``; the
second mission of a world merges into the first; both are uploaded under the world's name, so the
two jobs of a map run one after another). For every worker count (rounds interleaved: 1, 2, 1, 2,
...) it creates a fresh PostgreSQL schema, starts one ``mapserver serve --jobs celery`` and that many
``mapserver worker --concurrency 1`` processes on this machine's Redis, uploads the 8 logs back to back
and waits until every job is done. Figures (from the database clock): makespan (first upload to
last job done), jobs/hour and frames/s of the cluster, upload-to-done p50/p99, run time per job, and
what the database stored and wrote per frame and per merge (``pg_total_relation_size`` and
``pg_stat_user_tables`` of the schema). Last line: one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import sqlalchemy as sa

from mapserver.store import open_database
from mapserver.store.tokens import create_token

MAPSERVER = str(Path(sys.executable).with_name("mapserver"))
PG = os.environ.get("MAPSERVER_TEST_PG", "postgresql+psycopg://postgres@127.0.0.1:5432/test")


def simulate_logs(folder: Path, missions: tuple[float, float] = (2.0, 1.5)) -> tuple[list[Path], str]:
    """Write 8 loop logs: worlds 1-4, two missions each (``missions`` laps); return them and the scenario's preset."""
    from mapserver.ingest.simulator import simulate

    logs, preset = [], "irat"
    for laps in missions:
        for seed in (1, 2, 3, 4):
            out = folder / f"laps{laps}" / f"w{seed}"
            if not (out / "scenario.json").exists():
                simulate("loop", out, seed=seed, params={"laps": laps})
            preset = json.loads((out / "scenario.json").read_text())["preset"]
            logs.append(out / "single.bag")
    return logs, preset


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def spawn(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen([MAPSERVER, *args], stdout=log.open("ab"), stderr=subprocess.STDOUT,
                            start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})  # fmt: skip


def stop(processes: list[subprocess.Popen[bytes]]) -> None:
    for p in processes:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
    for p in processes:
        try:
            p.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(10)


def db_figures(engine: sa.Engine, schema: str) -> dict[str, dict[str, int]]:
    """Return bytes, rows inserted and rows updated per table of the schema."""
    time.sleep(1.5)  # table statistics reach pg_stat_user_tables within about a second
    with engine.connect() as conn:
        rows = conn.execute(sa.text(
            "SELECT relname, pg_total_relation_size(relid), n_tup_ins, n_tup_upd FROM pg_stat_user_tables "
            "WHERE schemaname = :s"), {"s": schema}).all()  # fmt: skip
    return {name: {"bytes": int(b), "inserted": int(i), "updated": int(u)} for name, b, i, u in rows}


def run_config(workers: int, logs: list[Path], preset: str, broker: str, tmp: Path, merge: bool) -> dict[str, Any]:
    """Run the 8 uploads on a fresh schema with ``workers`` workers; return the figures."""
    schema = f"bench_{uuid.uuid4().hex[:10]}"
    engine = sa.create_engine(PG)
    with engine.begin() as conn:
        conn.execute(sa.text(f'CREATE SCHEMA "{schema}"'))
    url = f"{PG}?options=-csearch_path%3D{schema}"
    queue = f"bench-{schema}"
    port = free_port()
    common = ["--db", url, "--broker", broker, "--queue", queue]
    processes = [spawn(["worker", *common, "--concurrency", "1", "--name", f"w{k}-{queue}@bench",
                        "--log-level", "warning"], tmp / f"{schema}-w{k}.log") for k in range(workers)]  # fmt: skip
    processes.append(spawn(["serve", *common, "--jobs", "celery", "--port", str(port), "--upload-dir",
                            str(tmp / schema), "--log-level", "warning"], tmp / f"{schema}-api.log"))  # fmt: skip
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                health = httpx.get(base + "/healthz", timeout=5).json()
                if len(health.get("workers", [])) == workers:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.5)
        else:
            raise SystemExit(f"cluster with {workers} workers did not start (logs in {tmp})")
        with open_database(url) as db, db.write() as conn:
            token, _ = create_token(conn=conn, scope="write")
        headers = {"Authorization": f"Bearer {token}"}
        jobs = []
        for log in logs:
            fields = {"preset": preset, "merge": str(merge).lower()}
            with log.open("rb") as handle:
                response = httpx.post(base + "/v1/sessions", files={"file": (f"{log.parent.name}.bag", handle)},
                                      data=fields, headers=headers, timeout=60)  # fmt: skip
            response.raise_for_status()
            jobs.append(response.json())
        states = wait_for_jobs(base, headers, [j["job"] for j in jobs])
        maps = httpx.get(base + "/v1/maps", headers=headers, timeout=30).json()["maps"]
    finally:
        stop(processes)
    figures = db_figures(engine, schema)
    reruns = sum(p.read_text(errors="replace").count("processing the log again") for p in tmp.glob(f"{schema}-w*.log"))
    with engine.begin() as conn:
        conn.execute(sa.text(f'DROP SCHEMA "{schema}" CASCADE'))
    engine.dispose()
    return {**summarise(workers, jobs, states, maps, figures), "merge": merge, "stale_reruns": reruns}


def wait_for_jobs(base: str, headers: dict[str, str], ids: list[str]) -> list[dict[str, Any]]:
    """Poll ``GET /v1/jobs/{id}`` until every job has ended; return their last states.

    The bench shares the machine with what it measures: one kept-alive client, and only the jobs not yet
    ended are asked for, at most once a second (a fresh ``httpx.get`` per job took 10-25 % of a core,
    measured with ``top``). The figures come from the database clock, so polling slower changes none.
    """
    final: dict[str, dict[str, Any]] = {}
    with httpx.Client(base_url=base, headers=headers, timeout=10) as client:
        while len(final) < len(ids):
            for job in ids:
                if job in final:
                    continue
                state = client.get(f"/v1/jobs/{job}").json()
                if state["status"] not in ("done", "failed"):
                    break  # jobs end roughly in upload order: ask again later
                final[job] = state
            else:
                continue
            time.sleep(1.0)
    return [final[job] for job in ids]


def _stamp(text: str) -> float:
    from datetime import datetime

    return datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()


def summarise(workers: int, jobs: list[dict[str, Any]], states: list[dict[str, Any]], maps: list[dict[str, Any]],
              figures: dict[str, dict[str, int]]) -> dict[str, Any]:  # fmt: skip
    failed = [s for s in states if s["status"] != "done"]
    created = np.array([_stamp(s["created_at"]) for s in states])
    started = np.array([_stamp(s["started_at"]) for s in states])
    finished = np.array([_stamp(s["finished_at"]) for s in states])
    frames = int(sum(j["frames"] for j in jobs))
    makespan = float(finished.max() - created.min())
    wait = finished - created
    merges = sum(1 for m in maps for _ in range(max(m["sessions"] - 1, 0)))
    state_bytes = sum(figures.get(t, {}).get("bytes", 0) for t in
                      ("sessions", "templates", "experiences", "links", "pose_cell_links", "map_states", "evidence"))
    merge_bytes = sum(figures.get(t, {}).get("bytes", 0) for t in ("merge_events", "merge_event_sessions",
                                                                   "map_archives"))  # fmt: skip
    return {
        "workers": workers, "jobs": len(states), "failed": len(failed), "frames": frames,
        "makespan_s": round(makespan, 2), "jobs_per_hour": round(3600 * len(states) / makespan, 1),
        "frames_per_s": round(frames / makespan, 1),
        "upload_to_done_p50_s": round(float(np.percentile(wait, 50)), 2),
        "upload_to_done_p99_s": round(float(np.percentile(wait, 99)), 2),
        "run_s_mean": round(float(np.mean(finished - started)), 2),
        "job_frames_per_s": round(float(np.mean([j["frames"] for j in jobs] / (finished - started))), 1),
        "maps": len(maps), "merges": merges,
        "db_bytes_per_frame": round(state_bytes / frames), "db_bytes_per_merge": round(merge_bytes / max(merges, 1)),
        "db_rows_written_per_frame": round(sum(f["inserted"] + f["updated"] for f in figures.values()) / frames, 2),
        "job_row_updates_per_job": round(figures.get("jobs", {}).get("updated", 0) / len(states), 1),
        "per_job": [{"frames": j["frames"], "queued_s": round(float(c - created.min()), 2),
                     "start_s": round(float(a - created.min()), 2), "run_s": round(float(b - a), 2)}
                    for j, c, a, b in zip(jobs, created, started, finished, strict=True)],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", default="1,2", help="worker counts to compare (default: 1,2)")
    parser.add_argument("--rounds", type=int, default=1, help="interleaved rounds (default: 1)")
    parser.add_argument("--broker", default="redis://127.0.0.1:6379/0")
    parser.add_argument("--no-merge", action="store_true", help="upload with merge=false (no atlas conflicts)")
    parser.add_argument("--keep-logs", type=Path, help="simulate the logs here once and reuse them")
    parser.add_argument("--laps", default="2,1.5", help="laps of each world's two missions (default: 2,1.5; jobs "
                        "that run a second or two measure the cluster's fixed costs more than its throughput)")
    args = parser.parse_args()
    first, second = (float(v) for v in args.laps.split(","))
    counts = [int(w) for w in args.workers.split(",")]
    with tempfile.TemporaryDirectory(prefix="bench-cluster-") as scratch:
        tmp = Path(scratch)
        logs, preset = simulate_logs(args.keep_logs or tmp / "logs", (first, second))
        results = []
        for _ in range(args.rounds):
            for workers in counts:
                result = run_config(workers, logs, preset, args.broker, tmp, not args.no_merge)
                results.append(result)
                print(f"{workers} worker(s): {result['jobs']} jobs ({result['failed']} failed), "
                      f"{result['frames']} frames in {result['makespan_s']} s → {result['frames_per_s']} frames/s, "
                      f"{result['jobs_per_hour']} jobs/h; upload→done p50 {result['upload_to_done_p50_s']} s, "
                      f"p99 {result['upload_to_done_p99_s']} s; {result['maps']} maps, {result['merges']} merges; "
                      f"DB {result['db_bytes_per_frame']} B/frame, {result['db_bytes_per_merge']} B/merge",
                      flush=True)  # fmt: skip
    by = {w: [r for r in results if r["workers"] == w] for w in counts}
    best = {w: max(r["frames_per_s"] for r in rs) for w, rs in by.items()}
    speedup = {f"{w}v{counts[0]}": round(best[w] / best[counts[0]], 2) for w in counts[1:]}
    # rounds are interleaved (1, 2, 1, 2, ...): each round's ratio compares runs minutes apart on the same machine
    paired = {f"{w}v{counts[0]}": [round(r["frames_per_s"] / b["frames_per_s"], 2) for r, b in
                                   zip(by[w], by[counts[0]], strict=True)] for w in counts[1:]}  # fmt: skip
    for key, ratios in paired.items():
        print(f"speed-up {key} per round: {', '.join(f'{r:.2f}' for r in ratios)}; median {np.median(ratios):.2f}")
    print(json.dumps({"results": results, "speedup_best": speedup, "speedup_per_round": paired}))


if __name__ == "__main__":
    main()

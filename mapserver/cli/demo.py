"""``mapserver demo --db URL [--if-empty]``: build a small demo atlas from two simulated missions.

The ``ellipse`` scenario (Menezes et al.'s Virtual Tour) is simulated with a short second session:
session A drives 3/4 of the loop, session B starts in the unmapped quarter and drives one lap over A's
route. Both are processed into the database as ``process --db`` does, so B merges into A's map online
(one map, two sessions, one merge event); the map is called ``demo``.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from mapserver.cli._output import emit_json, info
from mapserver.cli._progress import progress_bar
from mapserver.params import resolve_params
from mapserver.processing import pipeline
from mapserver.store import DEFAULT_DB_URL, list_maps, open_database

DEMO_SCENARIO = "ellipse"
DEMO_SEED = 7
DEMO_PARAMS: dict[str, float] = {"single_laps": 0.05, "session1_laps": 0.75, "session2_laps": 1.0}
DEMO_MAP = "demo"
DEMO_LOGS = (("session1", "demo-a.bag"), ("session2", "demo-b.bag"))


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``demo`` command."""
    parser = subparsers.add_parser("demo", help="build a small demo atlas from two simulated missions")
    parser.add_argument("--db", default=DEFAULT_DB_URL, help=f"SQLAlchemy URL (default: {DEFAULT_DB_URL})")
    parser.add_argument("--if-empty", action="store_true", help="do nothing when the database holds a map already")
    parser.add_argument("--json", action="store_true", help="print the JSON result as the last line of stdout")
    parser.set_defaults(func=run)


def build_demo(db_url: str) -> dict[str, Any]:
    """Simulate the demo missions and process them into ``db_url``; return a summary."""
    from mapserver.ingest.simulator import simulate

    started = time.perf_counter()
    folder = Path(tempfile.mkdtemp(prefix="mapserver-demo-"))
    try:
        info(f"simulating two {DEMO_SCENARIO} missions ...")
        scenario = simulate(DEMO_SCENARIO, folder, seed=DEMO_SEED, params=DEMO_PARAMS)
        logs = {s["name"]: folder / s["log"] for s in scenario["sessions"]}
        params = resolve_params(scenario["preset"])
        results = []
        for k, (session, name) in enumerate(DEMO_LOGS):
            log = logs[session].rename(folder / name)
            update, close = progress_bar(f"processing {name}")
            try:
                result = pipeline.process_into_store(
                    log, params, db_url=db_url, map_name=DEMO_MAP if k == 0 else f"{DEMO_MAP}-{k + 1}",
                    progress=update,
                )  # fmt: skip
            finally:
                close()
            results.append(result.summary())
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return {"sessions": results, "seconds": round(time.perf_counter() - started, 1)}


def run(args: argparse.Namespace) -> int:
    """Build the demo atlas (or skip it with ``--if-empty`` when maps exist, deleted ones included)."""
    with open_database(args.db) as db, db.read() as conn:
        maps = list_maps(conn=conn)
        archived = list_maps(conn=conn, archived=True)
    if args.if_empty and (maps or archived):
        info(f"the database holds {len(maps)} map(s) and {len(archived)} deleted one(s) already; no demo built")
        if args.json:
            emit_json({"built": False, "maps": [m.as_dict() for m in maps]})
        return 0
    summary = build_demo(args.db)
    with open_database(args.db) as db, db.read() as conn:
        maps = list_maps(conn=conn)
    listing = ", ".join(f"{m.name} ({m.sessions} sessions, {m.experiences} experiences)" for m in maps)
    info(f"demo atlas built in {summary['seconds']} s: {listing}")
    if args.json:
        emit_json({"built": True, "maps": [m.as_dict() for m in maps], "seconds": summary["seconds"]})
    return 0

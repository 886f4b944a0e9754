"""Offline merges (``mapserver merge --map session2 --into session1``) on the look-alike and overlap scenarios.

Usage: python bench/offline_merge_sweep.py SCENARIO [--seeds 0,1,2] [--sim K=V,...] [--preset P] [--set K=V,...]
       [--into-seed-offset N] [--merge-evidence M]

Per seed: simulate SCENARIO (``--sim``: simulator parameters), process its sessions 1 and 2 each alone into one
database (``process --no-merge``, preset ``P``: default the scenario's, ``--set``: parameter changes), measure
each map's APE against its own ground truth, then merge session 2's map into session 1's offline with the
contract's command. A merge is printed with its transform's error against the true alignment of the two map
frames (at session 2's origin: it includes session 2's drift up to the anchor) and the merged map's APE against
both sessions' ground truth (one rigid alignment); a refusal with its reason (exit 2). In ``twin`` every merge
is false. ``--into-seed-offset N``: session 1 comes from seed s + N instead (another world of the same shape:
every merge is false). ``--merge-evidence M``: passed to ``merge`` (metres; default: the map's parameter).
Last stdout line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the tests' measuring helpers

from core import preset
from tests.mapserver.merge.scenario_metrics import cli_code, cli_json, true_alignment


def _pairs(text: str) -> list[str]:
    return [p for p in text.split(",") if p] if text else []


def _ape(directory: Path, db: str, name: str, sessions: list[dict[str, Any]], tag: str) -> float:
    """APE RMSE of stored map ``name`` against the ground truth of ``sessions`` (one rigid alignment)."""
    doc = directory / f"{tag}.json"
    cli_json("export", "--db", db, "--map", name, "--format", "json", "--out", str(doc))
    gt = directory / f"{tag}.gt.tum"
    gt.write_text("".join((Path(s["dir"]) / s["ground_truth"]).read_text() for s in sessions))
    return round(float(cli_json("evaluate", str(doc), "--ground-truth", str(gt))["ape_rmse"]), 3)


def _place_error(out: Path, seed: int, match: dict[str, Any], sessions: list[dict[str, Any]]) -> float:
    """Metres, in the world, between where session 2 truly was at the merge's anchor and the stored place it was
    identified with: session 1's experience ``stored_experience`` (its ground truth when made) against session 2's
    experience nearest the anchor pose (its ground truth then). A true merge onto a drifted map is still near 0."""
    from mapserver.formats import read_tum

    def truth_at(session: dict[str, Any], stamp: float) -> np.ndarray:
        gt = read_tum(Path(session["dir"]) / session["ground_truth"])
        return np.asarray(gt.positions_xyz[int(np.argmin(np.abs(gt.stamps_s - stamp)))])

    s1 = json.loads((out / f"seed{seed}-s1.json").read_text())["experiences"]
    s2 = json.loads((out / f"seed{seed}-s2.json").read_text())["experiences"]
    stored = next(e for e in s1 if e["id"] == match["stored_experience"])
    pose = np.asarray(match["partial_pose"][:2])
    seen = s2[int(np.argmin([np.hypot(e["x"] - pose[0], e["y"] - pose[1]) for e in s2]))]
    return round(float(np.linalg.norm(truth_at(sessions[0], stored["stamp"])[:2]
                                      - truth_at(sessions[1], seen["stamp"])[:2])), 3)  # fmt: skip


def _transform(db: str) -> tuple[np.ndarray, dict[str, Any], dict[str, Any]]:
    """Return the (x, y, z, yaw) of the database's one merge event, its offline evidence and its match."""
    from mapserver.store import open_database
    from mapserver.store.merge_events import list_merge_events

    with open_database(db) as database, database.read() as conn:
        event = list_merge_events(conn=conn)[-1]
    evidence = ((event.details or {}).get("evidence") or {}).get("offline") or {}
    return np.array([*event.transform[:3], event.yaw], dtype=np.float64), evidence, (event.details or {})["match"]


def run_seed(out: Path, args: argparse.Namespace, seed: int) -> dict[str, Any]:
    """Simulate, process both sessions alone, merge offline; return the seed's figures."""
    sim = [f"--param={p}" for p in _pairs(args.sim)]
    sessions = []
    for number, s in ((1, seed + args.into_seed_offset), (2, seed)):
        directory = out / f"seed{s}"
        if not directory.exists():
            cli_json("simulate", args.scenario, "--out", str(directory), "--seed", str(s), *sim)
        info = json.loads((directory / "scenario.json").read_text())
        sessions.append({**info["sessions"][number - 1], "dir": str(directory)})
        p = args.preset or info["preset"]
    db = f"sqlite:///{out}/seed{seed}.sqlite"
    sets = [f"--set={kv}" for kv in _pairs(args.set)]
    for number, session in enumerate(sessions, 1):
        log = str(Path(session["dir"]) / session["log"])
        cli_json("process", log, "--db", db, "--preset", p, "--no-merge", "--map", f"s{number}", *sets)
    alone = [_ape(out, db, f"s{n}", [sessions[n - 1]], f"seed{seed}-s{n}") for n in (1, 2)]
    evidence = [] if args.merge_evidence is None else ["--merge-evidence", str(args.merge_evidence)]
    code, err = cli_code("merge", "--db", db, "--map", "s2", "--into", "s1", *evidence)
    row: dict[str, Any] = {"seed": seed, "merged": code == 0, "alone_ape_m": alone}
    if code != 0:
        row["reason"] = err.strip().splitlines()[-1][:300] if err.strip() else f"exit {code}"
        return row
    truth = true_alignment(Path(sessions[0]["dir"]), sessions[0], sessions[1],
                           math.radians(preset(p).exp_initial_em_deg))  # fmt: skip
    t, row["evidence"], match = _transform(db)
    row["place_error_m"] = _place_error(out, seed, match, sessions)
    row["transform_error_m"] = round(float(np.linalg.norm(t[:2] - truth[:2])), 3)
    row["transform_error_deg"] = round(abs(math.degrees(math.remainder(t[3] - truth[3], math.tau))), 1)
    if args.into_seed_offset == 0:
        row["merged_ape_m"] = _ape(out, db, "s1", sessions, f"seed{seed}-merged")
    return row


def main() -> None:
    """Print one line per seed, then the JSON of every figure."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenario")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--sim", default="", help="simulator parameters K=V,...")
    parser.add_argument("--preset", default="", help="engine preset (default: the scenario's)")
    parser.add_argument("--set", default="", help="parameter changes K=V,...")
    parser.add_argument("--into-seed-offset", type=int, default=0, help="session 1 from seed s + N (another world)")
    parser.add_argument("--merge-evidence", type=float, default=None, help="merge --merge-evidence M (metres)")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in (int(s) for s in args.seeds.split(",")):
            row = run_seed(Path(tmp), args, seed)
            rows.append(row)
            print(json.dumps(row), flush=True)
    merged = [r for r in rows if r["merged"]]
    print(json.dumps({"scenario": args.scenario, "sim": args.sim, "preset": args.preset, "set": args.set,
                      "into_seed_offset": args.into_seed_offset, "merged": len(merged), "seeds": len(rows),
                      "rows": rows}))  # fmt: skip


if __name__ == "__main__":
    main()

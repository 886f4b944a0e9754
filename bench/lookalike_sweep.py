"""False and true merges of the merge decision on the look-alike scenarios (issue 12), swept over strength.

Usage: python bench/lookalike_sweep.py [--out DIR] [--seeds 3] [--rows twin:5,twin:10,...] [--param K=V,...]

Each row is ``SCENARIO`` or ``SCENARIO:STRENGTH`` (``lookalike_m`` for twin, ``symmetric_deg`` for
symmetric). Per seed it runs the contract's commands: ``mapserver simulate SCENARIO --out D --seed N
--param ...``, ``mapserver process D/session1.bag --db sqlite:///D/db.sqlite`` and ``mapserver process
D/session2.bag --db sqlite:///D/db.sqlite --json``, then classifies session 2's merges against the ground
truth: in ``twin`` every merge is false (the places never overlap); elsewhere a merge is false when its
transform is more than ``--tol-m`` metres or ``--tol-deg`` degrees from the true alignment of the two
sessions' map frames, except that an applied merge is judged where it put the robot: false when session 2's
experiences within 10 s of it lie, in the final map, more than ``--tol-m`` metres (median) from their true
positions in session 1's map frame (the error at the map origin grows with the drift before the merge).
Prints one line per row and, last, one JSON object with every figure.
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
from tests.mapserver.merge.scenario_metrics import cli_json, true_alignment

STRENGTH = {"twin": "lookalike_m", "twin-overlap": "lookalike_m", "symmetric": "symmetric_deg",
            "symmetric-overlap": "symmetric_deg"}  # fmt: skip
DEFAULT_ROWS = ("twin:5,twin:10,twin:20,twin:40,twin-overlap:5,twin-overlap:20,twin-overlap:40,"
                "symmetric,symmetric-overlap")  # fmt: skip


def _shared_distance(directory: Path, s1: dict, s2: dict, until: float, radius: float = 2.0) -> float:
    """Metres session 2 drove within ``radius`` of session 1's true path, up to log time ``until``."""
    from scipy.spatial import cKDTree

    a, b = np.loadtxt(directory / s1["ground_truth"]), np.loadtxt(directory / s2["ground_truth"])
    b = b[b[:, 0] <= until]
    if len(b) < 2:
        return 0.0
    near = cKDTree(a[:, 1:3]).query(b[:, 1:3])[0] <= radius
    steps = np.linalg.norm(np.diff(b[:, 1:3], axis=0), axis=1)
    return float(steps[near[1:]].sum())


def _ape(directory: Path, db: str, map_name: str, sessions: list[dict], tag: str) -> float:
    """APE RMSE of a stored map against the ground truth of the given sessions (one rigid alignment)."""
    doc = directory / f"{tag}.json"
    cli_json("export", "--db", db, "--map", map_name, "--format", "json", "--out", str(doc))
    gt = directory / f"{tag}.gt.tum"
    gt.write_text("".join((directory / s["ground_truth"]).read_text() for s in sessions))
    return float(cli_json("evaluate", str(doc), "--ground-truth", str(gt))["ape_rmse"])


def _local_error(directory: Path, doc: dict, s1: dict, s2: dict, stamp: float, window_s: float = 10.0) -> float | None:
    """Median distance (m) from session 2's experiences within ``window_s`` of ``stamp`` in the final map to
    their true positions in session 1's map frame (None: no such experience).

    The transform's error at the map origin (``error_m``) grows with session 2's odometry drift before the
    merge; this says whether the merge put the robot in the right place.
    """
    from core.se3 import compose, inverse
    from mapserver.formats import yaw_from_quaternion

    final = json.loads((directory / "final.json").read_text())
    near = [e for e in final["experiences"] if e["session"] == s2["name"] and abs(e["stamp"] - stamp) <= window_s]
    if not near:
        return None
    gt1, gt2 = (np.loadtxt(directory / s["ground_truth"]).reshape(-1, 8) for s in (s1, s2))
    start = np.array([*gt1[0, 1:4], yaw_from_quaternion(*gt1[0, 4:8])])
    frame = compose(np.array([0.0, 0.0, 0.0, math.radians(preset(doc["preset"]).exp_initial_em_deg)]), inverse(start))
    errors = []
    for e in near:
        row = gt2[int(np.argmin(np.abs(gt2[:, 0] - e["stamp"])))]
        true = compose(frame, np.array([*row[1:4], yaw_from_quaternion(*row[4:8])]))
        errors.append(math.hypot(e["x"] - true[0], e["y"] - true[1]))
    return round(float(np.median(errors)), 3)


def run_once(
    out: Path, scenario: str, strength: float | None, seed: int, tol_m: float, tol_deg: float, extra: str = ""
) -> dict:
    """Simulate one seed of a row, process its two sessions into one database, classify the merges.

    A merge counts as surviving when its status is ``applied``; ``rejected`` ones were rolled back by their
    verification. Also: metres session 2 drove on session 1's ground before its first surviving merge,
    the APE of session 2's final map and the APE of session 2 processed alone (twin) or of the ``single``
    route (the others).
    """
    directory = out / f"{scenario}-{strength if strength is not None else 'default'}-seed{seed}"
    argv = ["simulate", scenario, "--out", str(directory), "--seed", str(seed)]
    given = [f"{STRENGTH[scenario]}={strength}"] if strength is not None else []
    given += [extra] if extra else []
    if given:
        argv += ["--param", ",".join(given)]
    doc = cli_json(*argv)
    db = f"sqlite:///{directory / 'db.sqlite'}"
    s1, s2 = doc["sessions"][:2]
    cli_json("process", str(directory / s1["log"]), "--db", db)
    result = cli_json("process", str(directory / s2["log"]), "--db", db)
    truth = true_alignment(directory, s1, s2, math.radians(preset(doc["preset"]).exp_initial_em_deg))
    merges = []
    for merge in result["merges"]:
        t = merge["transform"]
        err_m = float(np.hypot(t["x"] - truth[0], t["y"] - truth[1]))
        err_deg = abs(math.degrees(math.remainder(t["yaw"] - truth[3], 2 * math.pi)))
        false = scenario == "twin" or err_m > tol_m or err_deg > tol_deg
        merges.append({"frame": merge["frame"], "error_m": round(err_m, 2), "error_deg": round(err_deg, 1),
                       "false": false, "status": merge.get("status", "applied"), "stamp": merge["stamp"]})  # fmt: skip
    applied = [m for m in merges if m["status"] == "applied"]
    shared = _shared_distance(directory, s1, s2, applied[0]["stamp"]) if applied else None
    in_map = [s1, s2] if applied else [s2]
    ape = _ape(directory, db, result["map"], in_map, "final")
    for m in applied:  # where the merge put session 2, judged in the final map near the merge
        m["local_error_m"] = _local_error(directory, doc, s1, s2, m["stamp"])
        if scenario != "twin" and m["local_error_m"] is not None:
            m["false"] = m["local_error_m"] > tol_m
    alone_db = f"sqlite:///{directory / 'alone.sqlite'}"
    reference = doc["single"] if scenario != "twin" and doc.get("single") else s2
    cli_json("process", str(directory / reference["log"]), "--db", alone_db, "--no-merge")
    ref_name = Path(reference["log"]).name.split(".")[0]
    ape_alone = _ape(directory, alone_db, ref_name, [reference], "alone")
    return {"seed": seed, "merges": merges, "shared_m_before_merge": shared, "ape": ape, "ape_reference": ape_alone}


def main() -> None:
    """Run the rows and print the table."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--rows", default=DEFAULT_ROWS)
    parser.add_argument("--tol-m", type=float, default=5.0)
    parser.add_argument("--tol-deg", type=float, default=30.0)
    parser.add_argument("--param", default="", help="more simulator parameters for every row, e.g. lookalike_turns=1")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="lookalike-"))
    figures: dict[str, Any] = {}
    for row in args.rows.split(","):
        scenario, _, value = row.partition(":")
        strength = float(value) if value else None
        runs = [run_once(out, scenario, strength, seed, args.tol_m, args.tol_deg, args.param)
                for seed in range(args.first_seed, args.first_seed + args.seeds)]  # fmt: skip
        surviving = sum(any(m["false"] and m["status"] == "applied" for m in r["merges"]) for r in runs)
        rolled = sum(any(m["false"] and m["status"] == "rejected" for m in r["merges"]) for r in runs)
        true = sum(any(not m["false"] and m["status"] == "applied" for m in r["merges"]) for r in runs)
        shared = [r["shared_m_before_merge"] for r in runs if r["shared_m_before_merge"] is not None]
        ratios = [r["ape"] / r["ape_reference"] for r in runs]
        figures[row] = {"seeds": len(runs), "runs_with_surviving_false_merge": surviving,
                        "runs_with_false_merge_rolled_back": rolled, "runs_with_true_merge": true,
                        "shared_m_before_merge": shared, "ape_ratio": ratios, "runs": runs}  # fmt: skip
        med = f"{np.median(shared):.1f}/{max(shared):.1f}" if shared else "-"
        print(f"{row:<20} seeds {len(runs)}  surviving false {surviving}  rolled back {rolled}  true {true}  "
              f"shared m before merge (median/max) {med}  APE ratio median {np.median(ratios):.2f} "
              f"max {max(ratios):.2f}", flush=True)  # fmt: skip
    print(json.dumps(figures))


if __name__ == "__main__":
    main()

"""False and true merges of the merge decision on the look-alike scenarios (issue 12), swept over strength.

Usage: python bench/lookalike_sweep.py [--out DIR] [--seeds 3] [--rows twin:5,twin:10,...] [--param K=V,...]
[--set K=V,...] [--alone] [--floor]

Each row is ``SCENARIO`` or ``SCENARIO:STRENGTH`` (``lookalike_m`` for twin, ``symmetric_deg`` for
symmetric). Per seed it runs the contract's commands: ``mapserver simulate SCENARIO --out D --seed N
--param ...``, ``mapserver process D/session1.bag --db sqlite:///D/db.sqlite`` and ``mapserver process
D/session2.bag --db sqlite:///D/db.sqlite --json``, then classifies session 2's merges against the ground
truth: in ``twin`` every merge is false (the places never overlap); elsewhere a merge is judged by the place
it put the robot at: false when the stored experience nearest to the robot's pose carried into the stored map
by the merge transform was seen, in the world, more than ``--tol-m`` metres from where the robot truly was at
the merge, or the merge turns the robot against that experience ``--tol-deg`` degrees off the truth
(``place_error_m``, ``place_error_deg``). Also reported: the transform's error against the true alignment of
the two sessions' map frames (``error_m``, ``error_deg``: it grows with either session's drift before the
merge) and, for an applied merge, the final map's error near it (``local_error_m``: the median distance of
session 2's experiences within 10 s of it from their true positions in session 1's map frame, which counts the
stored map's own drift; until 2026-11-26 this judged applied merges, and called a merge onto the right place of
a map drifted 9 m there false). With ``--alone`` each merged run also processes both sessions alone and prints
them against their parts of the merged map (each part aligned on its own): whether a merge made either
session's ground worse, apart from the single route's own odometry noise. With ``--floor`` each run also prints the
closure floor of the final map and of its reference (:mod:`tests.mapserver.merge.closure_floor`: each re-solved with
every loop and merge link replaced by the truth), so an APE ratio can be told apart from the ratio of the two
odometry draws.
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
from core.angles import wrap_angle_exact
from tests.mapserver.merge.closure_floor import closure_floor_of
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
    from core.se3 import compose, inverse, yaw_from_quaternion

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


def _place_error(
    stored: dict, truth: tuple[np.ndarray, np.ndarray], stamp: float, carried: np.ndarray
) -> tuple[float, float]:
    """Metres and degrees, in the world, between where session 2 truly was at ``stamp`` and the stored place the
    merge put it at.

    ``carried`` (x, y, z, yaw) is the robot's pose at the merge frame carried into the stored map by the merge
    transform; the stored place is session 1's experience nearest to it in the stored map as it was when the merge
    was made (``stored``); ``truth``: both sessions' ground truth (TUM rows). Metres: between the two sessions'
    ground-truth positions there (session 1's when it made that experience). Degrees: the merge's heading of the
    robot relative to that experience against the true one. Unlike the final map's error near the merge
    (``_local_error``), neither counts the stored map's own drift: a merge onto the right place of a drifted map is
    a true merge.
    """
    from core.se3 import yaw_from_quaternion

    gt1, gt2 = truth
    poses = np.array([[e["x"], e["y"]] for e in stored["experiences"]])
    nearest = stored["experiences"][int(np.argmin(np.linalg.norm(poses - carried[:2], axis=1)))]
    seen = gt1[int(np.argmin(np.abs(gt1[:, 0] - nearest["stamp"])))]
    truly = gt2[int(np.argmin(np.abs(gt2[:, 0] - stamp)))]
    turn_true = yaw_from_quaternion(*truly[4:8]) - yaw_from_quaternion(*seen[4:8])
    turn_merge = float(carried[3]) - nearest["yaw"]
    degrees = abs(math.degrees(wrap_angle_exact(turn_merge - turn_true)))
    return round(float(np.linalg.norm(seen[1:3] - truly[1:3])), 3), round(degrees, 1)


def _merge_poses(db: str) -> dict[int, np.ndarray]:
    """Each merge event's robot pose at its merge frame, carried into the stored map (event id → x, y, z, yaw).

    The pose carried is the robot's in the session's own map frame (``session_pose``), the frame the merge
    transform takes: once the session's map has closed a loop it is not the dead reckoning (``reckoning_pose``, used
    for events stored without ``session_pose``; traced on ``twin-overlap`` turns alike 40 m seed 14, where session 2's
    own closures in the self-aliased stretch moved its map 10 m and 53° from its dead reckoning).
    """
    from core.se3 import compose
    from mapserver.store import open_database
    from mapserver.store.merge_events import list_merge_events

    out = {}
    with open_database(db) as database, database.read() as conn:
        for event in list_merge_events(conn=conn):
            details = event.details or {}
            reckoning = details.get("session_pose", details.get("reckoning_pose"))
            if reckoning is not None:
                transform = np.array([event.transform[0], event.transform[1], event.transform[2], event.yaw])
                out[event.id] = compose(transform, np.asarray(reckoning, dtype=np.float64))
    return out


def _ape_alone(directory: Path, session: dict, set_args: list[str], tag: str) -> float:
    """APE RMSE of ``session``'s log processed on its own (``--no-merge``, database ``TAG.sqlite``)."""
    db = f"sqlite:///{directory / f'{tag}.sqlite'}"
    cli_json("process", str(directory / session["log"]), "--db", db, "--no-merge", *set_args)
    return _ape(directory, db, Path(session["log"]).name.split(".")[0], [session], tag)


def _sessions_alone(directory: Path, sessions: list[dict], set_args: list[str]) -> dict:
    """Each session processed alone (``--no-merge``) and its part of the final map, APE RMSE in metres.

    ``part``: the final map's experiences of that session aligned on their own (``evaluate --session``), so
    a part can be compared with the same session alone: what the merge did to that session's ground.
    """
    out = {}
    for s in sessions:
        alone = _ape_alone(directory, s, set_args, f"{s['name']}-alone")
        part = float(cli_json("evaluate", str(directory / "final.json"), "--ground-truth",
                              str(directory / "final.gt.tum"), "--session", s["name"])["ape_rmse"])  # fmt: skip
        out[s["name"]] = {"alone": round(alone, 3), "part": round(part, 3)}
    return out


def run_once(
    out: Path, scenario: str, strength: float | None, seed: int, tol_m: float, tol_deg: float, extra: str = "",
    settings: str = "", alone: bool = False, floor: bool = False,
) -> dict:
    """Simulate one seed of a row, process its two sessions into one database, classify the merges.

    A merge counts as surviving when its status is ``applied``; ``rejected`` ones were rolled back by their
    verification. Also: metres session 2 drove on session 1's ground before its first surviving merge,
    the APE of session 2's final map and the APE of session 2 processed alone (twin) or of the ``single``
    route (the others). ``settings`` (``--set``) go to every ``mapserver process``. ``alone``: also each
    session processed alone and its part of the final map (:func:`_sessions_alone`; merged runs only). ``floor``:
    also the closure floor of the final map and of the reference (:mod:`tests.mapserver.merge.closure_floor`).
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
    set_args = ["--set", settings] if settings else []
    first = cli_json("process", str(directory / s1["log"]), "--db", db, *set_args)
    stored_json = directory / "stored.json"
    cli_json("export", "--db", db, "--map", first["map"], "--format", "json", "--out", str(stored_json))
    stored = json.loads(stored_json.read_text())
    result = cli_json("process", str(directory / s2["log"]), "--db", db, *set_args)
    carried = _merge_poses(db)
    truth = true_alignment(directory, s1, s2, math.radians(preset(doc["preset"]).exp_initial_em_deg))
    merges = []
    for merge in result["merges"]:
        t = merge["transform"]
        err_m = float(np.hypot(t["x"] - truth[0], t["y"] - truth[1]))
        err_deg = abs(math.degrees(wrap_angle_exact(t["yaw"] - truth[3])))
        false = scenario == "twin" or err_m > tol_m or err_deg > tol_deg
        merges.append({"frame": merge["frame"], "error_m": round(err_m, 2), "error_deg": round(err_deg, 1),
                       "false": false, "status": merge.get("status", "applied"), "stamp": merge["stamp"]})  # fmt: skip
    applied = [m for m in merges if m["status"] == "applied"]
    shared = _shared_distance(directory, s1, s2, applied[0]["stamp"]) if applied else None
    in_map = [s1, s2] if applied else [s2]
    ape = _ape(directory, db, result["map"], in_map, "final")
    world = tuple(np.loadtxt(directory / s["ground_truth"]).reshape(-1, 8) for s in (s1, s2))
    for m, merge in zip(merges, result["merges"], strict=True):  # where the merge put session 2, in the world
        if merge["event"] in carried:
            m["place_error_m"], m["place_error_deg"] = _place_error(stored, world, m["stamp"], carried[merge["event"]])
            if scenario != "twin":
                m["false"] = m["place_error_m"] > tol_m or m["place_error_deg"] > tol_deg
    for m in applied:  # and in the final map near the merge (the stored map's own drift counts here)
        m["local_error_m"] = _local_error(directory, doc, s1, s2, m["stamp"])
    reference = doc["single"] if scenario != "twin" and doc.get("single") else s2
    ape_alone = _ape_alone(directory, reference, set_args, "alone")
    run = {"seed": seed, "merges": merges, "shared_m_before_merge": shared, "ape": ape, "ape_reference": ape_alone}
    if floor:
        run["floor"] = closure_floor_of(directory / "final.json", directory / "final.gt.tum")
        run["floor_reference"] = closure_floor_of(directory / "alone.json", directory / "alone.gt.tum")
    if alone and applied:
        run["sessions"] = _sessions_alone(directory, in_map, set_args)
    return run


def _print_floor(runs: list[dict]) -> None:
    """Print per seed the APE ratio beside the closure floors' ratio (what the two odometry draws alone give)."""
    for r in runs:
        f, g = r["floor"], r["floor_reference"]
        ratio = r["ape"] / r["ape_reference"]
        print(f"  seed {r['seed']:<3} APE {r['ape']:.3f} / {r['ape_reference']:.3f} = {ratio:.2f}"
              f"   floor {f['floor']:.3f} / {g['floor']:.3f} = {f['floor'] / g['floor']:.2f}"
              f"   APE over floor {r['ape'] / f['floor']:.2f} / {r['ape_reference'] / g['floor']:.2f}", flush=True)


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
    parser.add_argument("--set", dest="settings", default="",
                        help="engine parameters for every process run, e.g. vt_shift_heading=1,exp_relax_joint=1")
    parser.add_argument("--alone", action="store_true",
                        help="also process each session alone and print it against its part of the merged map")
    parser.add_argument("--floor", action="store_true",
                        help="also the closure floor of each final map and its reference: the APE with every loop and "
                             "merge link replaced by the truth (what the odometry draw leaves)")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="lookalike-"))
    figures: dict[str, Any] = {}
    for row in args.rows.split(","):
        scenario, _, value = row.partition(":")
        strength = float(value) if value else None
        runs = [run_once(out, scenario, strength, seed, args.tol_m, args.tol_deg, args.param, args.settings, args.alone,
                         args.floor)
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
        if args.floor:
            _print_floor(runs)
        for r in runs:
            if "sessions" in r:
                parts = "  ".join(f"{k}: alone {v['alone']:.2f}, in the map {v['part']:.2f}"
                                  for k, v in r["sessions"].items())
                print(f"  seed {r['seed']:<3} merged {r['ape']:.2f} / reference {r['ape_reference']:.2f} "
                      f"= {r['ape'] / r['ape_reference']:.2f}   {parts}", flush=True)
    print(json.dumps(figures))


if __name__ == "__main__":
    main()

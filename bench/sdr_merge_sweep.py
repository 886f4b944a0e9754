"""Online merges of sdr-htm maps on the look-alike and overlap scenarios, judged against the ground truth.

Usage: python bench/sdr_merge_sweep.py SCENARIO [--seeds 0,1,2] [--sim K=V,...] [--preset circle] [--set K=V,...]

Per seed: simulate SCENARIO (``--sim``: simulator parameters, e.g. ``lookalike_m=20,lookalike_turns=1``),
map session 1 alone with the preset (``--set``: parameter changes; default ``frontend=sdr-htm``), then run
session 2 through the online merge driver against it (``mapserver.merge.online.OnlineMerger``, the
driver ``process`` uses, without the database). Every merge is printed with its transform's error against
the true alignment of the two map frames (at the map origin: it grows with session 2's drift before the
merge) and with its place error (``place_error_m``/``_deg``: where it put the robot against where session 1 saw
that place; a false merge is metres to tens of metres off, a true one within a few), every rollback
with its reason, and the surviving merges with their verification status
(``passed``, or ``incomplete`` when the log ended during the probation and what it saw did not speak
against the merge; otherwise the log's end rolls it back). In ``twin`` every merge is false.
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

from core import Engine, preset
from core.se3 import yaw_from_quaternion
from mapserver.ingest.simulator.output import simulate
from mapserver.merge.engines import StoredMap
from mapserver.merge.online import MergeEvent, OnlineMerger, Rollback
from mapserver.processing.run import run_engine
from tests.mapserver.merge.scenario_metrics import true_alignment


def _pairs(text: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in filter(None, text.split(",")):
        key, value = item.split("=", 1)
        out[key] = value if not value.replace(".", "", 1).lstrip("-").isdigit() else float(value)
    return out


def place_error(
    stored: dict[str, np.ndarray], merged: Engine, truth: tuple[np.ndarray, np.ndarray], stamp: float
) -> tuple[float, float]:
    """Metres and degrees, in the world, between where session 2 truly was at ``stamp`` and the stored place the
    merge put it at: session 1's experience nearest to the robot's pose (its current experience plus the odometry
    since) in the merged map right after the merge
    (loaded experiences come first), as seen by session 1 in the ground truth; degrees: the robot's heading
    relative to that experience, merged against true (as ``bench/lookalike_sweep.py``'s ``place_error_m``: the
    stored map's own drift does not count)."""
    gt1, gt2 = truth
    n1 = int(np.shape(stored["em_stamp"])[0])
    poses = merged.map.poses
    here = merged.map.robot_pose()
    nearest = int(np.argmin(np.linalg.norm(poses[:n1, :3] - here[:3], axis=1)))
    seen = gt1[int(np.argmin(np.abs(gt1[:, 0] - float(stored["em_stamp"][nearest]))))]
    truly = gt2[int(np.argmin(np.abs(gt2[:, 0] - stamp)))]
    turn_true = yaw_from_quaternion(*truly[4:8]) - yaw_from_quaternion(*seen[4:8])
    turn_merge = float(here[3] - poses[nearest, 3])
    degrees = abs(math.degrees(math.remainder(turn_merge - turn_true, math.tau)))
    return round(float(np.linalg.norm(seen[1:3] - truly[1:3])), 2), round(degrees, 1)


def run_seed(out: Path, scenario: str, seed: int, sim: dict[str, Any], params: Any) -> dict[str, Any]:
    """Simulate one seed, map session 1, run session 2 through the merge driver; return its merges."""
    info = simulate(scenario, out, seed=seed, params=sim)
    s1, s2 = info["sessions"][:2]
    stored = Engine(params, origin=1)
    run_engine(stored, out / s1["log"])
    stored.settle()
    snapshot = stored.snapshot()
    merger = OnlineMerger([StoredMap(1, params, snapshot)])
    truth = true_alignment(out, s1, s2, math.radians(params.exp_initial_em_deg))
    worlds = (np.loadtxt(out / s1["ground_truth"], ndmin=2), np.loadtxt(out / s2["ground_truth"], ndmin=2))
    events: list[dict[str, Any]] = []

    def hook(frame: Any, result: Any) -> Engine | None:
        event = merger.observe(current[0], result, frame)
        if isinstance(event, MergeEvent):
            t = event.record.transform
            error_m = float(np.hypot(t[0] - truth[0], t[1] - truth[1]))
            error_deg = abs(math.degrees(math.remainder(t[3] - truth[3], math.tau)))
            place_m, place_deg = place_error(snapshot, event.engine, worlds, event.stamp)
            events.append({"frame": result.frame, "error_m": round(error_m, 2), "error_deg": round(error_deg, 1),
                           "place_error_m": place_m, "place_error_deg": place_deg})  # fmt: skip
            current[0] = event.engine
            return event.engine
        if isinstance(event, Rollback):
            events[-1]["rolled_back_at"] = result.frame
            events[-1]["reason"] = event.event.evidence["verification"]["reason"]
            current[0] = event.engine
            return event.engine
        return None

    current = [Engine(params, origin=2)]
    run = run_engine(current[0], out / s2["log"], on_step=hook)
    ended = merger.finish()  # a probation the log cut short is judged on what it saw
    if ended is not None:
        events[-1]["rolled_back_at"] = run.frames
        events[-1]["reason"] = ended.event.evidence["verification"]["reason"]
    surviving = [e for e in events if "rolled_back_at" not in e]
    for event, kept in zip(surviving, merger.events, strict=False):
        verification = kept.evidence.get("verification", {})
        event["status"] = verification.get("status")
        kept_keys = ("distance_m", "post_hit_m", "post_miss_m", "cusum_m", "held_frames")
        event["verification"] = {k: verification.get(k) for k in kept_keys}
    return {"seed": seed, "gate": [round(g, 3) for g in merger.sdr_gates.values()], "merges": events}


def main() -> None:
    """Run the seeds and print one line each, then the JSON."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenario")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--sim", default="")
    parser.add_argument("--preset", default="circle")
    parser.add_argument("--set", default="frontend=sdr-htm")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    params = preset(args.preset).replace(**_pairs(args.set))
    root = args.out or Path(tempfile.mkdtemp(prefix="sdr-merge-"))
    rows = []
    for seed in (int(s) for s in args.seeds.split(",")):
        row = run_seed(root / f"{args.scenario}-{seed}", args.scenario, seed, _pairs(args.sim), params)
        rows.append(row)
        label = f"{args.scenario} {args.sim or '-'} seed {seed} gate {row['gate']}"
        print(f"{label}: {json.dumps(row['merges'])}", flush=True)
    print(json.dumps({"scenario": args.scenario, "sim": args.sim, "preset": args.preset, "set": args.set,
                      "runs": rows}))  # fmt: skip


if __name__ == "__main__":
    main()

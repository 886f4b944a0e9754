"""How far the single-route reference of the look-alike sweeps moves with the odometry's noise alone (issue 12).

Usage: python bench/reference_spread.py [SCENARIO] [--seeds 10] [--first-seed 0] [--draws 3] [--out DIR]

``lookalike_sweep.py`` bounds a merged map's APE by 1.5× the APE of the scenario's ``single`` route (one
session driving both sessions' ground) on the same seed. That reference is one draw of the simulator's
per-session noise (odometry random walk, speed and lateral wobble, pixel noise); the vehicle's systematic
errors are shared by every session of a seed. This script asks what ratio the noise alone makes: per seed it
drives the ``single`` route again with ``--draws`` other noise draws (session indices 100, 101, …; the same
world, route and vehicle), processes each log alone (``mapserver process --no-merge``) and prints each draw's
APE against the reference draw's (the index ``mapserver simulate`` gives it, so that draw's APE is the sweep's
``ape_reference``). A map as good as a single session, on average, is over 1.5× its seed's reference as often
as these draws are. Prints one line per seed and, last, one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the tests' measuring helpers

from mapserver.ingest.simulator.output import plan_scenario, render_frames, simulate_session, write_ground_truth
from mapserver.ingest.simulator.scenarios import Plan
from mapserver.ingest.writer import write_log
from tests.mapserver.merge.scenario_metrics import cli_json


def _ape_of_draw(directory: Path, plan: Plan, seed: int, index: int) -> float:
    """Drive the plan's ``single`` route with the noise of session index ``index``; its APE RMSE alone."""
    if plan.single is None:
        msg = "the scenario has no single route"
        raise SystemExit(msg)
    drive = simulate_session(plan, plan.single, index, seed)
    log, gt = directory / f"single-{index}.bag", directory / f"single-{index}.tum"
    write_log(log, "bag", render_frames(plan, drive, seed, index), drive.odometry, drive.ground_truth)
    write_ground_truth(gt, drive)
    db = f"sqlite:///{directory / f'single-{index}.sqlite'}"
    result = cli_json("process", str(log), "--db", db, "--no-merge", "--preset", plan.preset)
    doc = directory / f"single-{index}.json"
    cli_json("export", "--db", db, "--map", result["map"], "--format", "json", "--out", str(doc))
    return float(cli_json("evaluate", str(doc), "--ground-truth", str(gt))["ape_rmse"])


def _reference_index(plan: Plan) -> int:
    """The session index ``mapserver simulate`` gives the single route (its noise draw)."""
    for index, session in enumerate(plan.sessions):
        if session is plan.single:
            return index
    return len(plan.sessions)


def main() -> None:
    """Run the seeds and print the table."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenario", nargs="?", default="symmetric-overlap")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--draws", type=int, default=3)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="reference-spread-"))
    runs: list[dict[str, Any]] = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        directory = out / f"{args.scenario}-seed{seed}"
        directory.mkdir(parents=True, exist_ok=True)
        plan = plan_scenario(args.scenario, seed)
        reference = _ape_of_draw(directory, plan, seed, _reference_index(plan))
        draws = [_ape_of_draw(directory, plan, seed, 100 + k) for k in range(args.draws)]
        ratios = [d / reference for d in draws]
        runs.append({"seed": seed, "reference": reference, "draws": draws, "ratios": ratios})
        print(f"seed {seed:<3} reference {reference:.3f}  draws " + " ".join(f"{d:.3f}" for d in draws)
              + "  ratios " + " ".join(f"{r:.2f}" for r in ratios), flush=True)  # fmt: skip
    ratios = np.array([r for run in runs for r in run["ratios"]])
    summary = {"scenario": args.scenario, "draws": int(ratios.size), "median_ratio": float(np.median(ratios)),
               "max_ratio": float(ratios.max()), "over_1_5": int((ratios > 1.5).sum()),
               "seeds_with_a_draw_over_1_5": sum(any(r > 1.5 for r in run["ratios"]) for run in runs)}  # fmt: skip
    print(f"{args.scenario}: {summary['draws']} draws, ratio to the reference median {summary['median_ratio']:.2f} "
          f"max {summary['max_ratio']:.2f}, over 1.5: {summary['over_1_5']} "
          f"(seeds with one: {summary['seeds_with_a_draw_over_1_5']} of {len(runs)})", flush=True)  # fmt: skip
    print(json.dumps({"summary": summary, "runs": runs}))


if __name__ == "__main__":
    main()

"""Issue 64: maps of AUV logs navigated by DVL + IMU + depth, against ground truth and their dead reckoning.

Usage: python bench/underwater_nav.py [--seeds 10] [--rows seabed,cave3d,cave3d-odometry] [--preset poseidon-lvc]

For each scenario and seed, simulates the single-session log with the navigation sensors and no wheel
odometry (``seabed``: its defaults; ``cave3d``: ``nav=1, odometry=0``), processes it with the preset (the
engine's motion is the complementary-filter fusion of :mod:`mapserver.ingest.fusion`), and evaluates the map
against the simulator's ground truth (:func:`mapserver.evaluation.maps.evaluate_map`: experiences aligned
rigidly, Umeyama 1991). The dead-reckoning baseline is the map JSON's ``odometry`` key: the fused motion of the
same sensors integrated frame by frame, aligned on its own. Per row: APE RMSE and APE-z RMSE of the map and of
the dead reckoning (median and worst over seeds), loop closures, DVL gaps. The last stdout line is one JSON
object with every row and every seed's figures.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mapserver.evaluation.maps import evaluate_map
from mapserver.formats import read_tum
from mapserver.ingest import open_log
from mapserver.ingest.simulator import simulate
from mapserver.params import resolve_params
from mapserver.processing.run import process_log

ROWS: dict[str, tuple[str, dict[str, float], str]] = {
    "seabed": ("seabed", {}, "navigation"),
    "cave3d": ("cave3d", {"nav": 1.0, "odometry": 0.0}, "navigation"),
    "cave3d-odometry": ("cave3d", {}, "odometry"),
}
"""Row name → (scenario, its parameters, the motion source the log must give). ``cave3d-odometry`` is the
scenario's default log (its drifting ``nav_msgs/Odometry``): the reference the fused rows are read against."""
FIGURES = ("ape_rmse", "odometry_ape_rmse", "ape_z_rmse", "odometry_ape_z_rmse")


def one(name: str, seed: int, preset: str, root: Path) -> dict[str, Any]:
    """Simulate, process and evaluate one seed of a row."""
    scenario, params, source = ROWS[name]
    out = root / f"{name}-{seed}"
    doc = simulate(scenario, out, seed=seed, params=params, only=["single"])
    log = out / doc["single"]["log"]
    with open_log(log) as opened:
        assert opened.motion_source == source, opened.mapping
        opened.verify()
        report = opened.navigation_report
        gaps = report.dvl_gaps if report is not None else 0
    started = time.perf_counter()
    result = process_log(log, resolve_params(preset))
    took = time.perf_counter() - started
    assert result.document is not None
    ev = evaluate_map(result.document, read_tum(out / doc["single"]["ground_truth"]))
    return {
        "seed": seed, "frames": result.frames, "experiences": result.experiences,
        "loop_closures": result.loop_closures, "dvl_gaps": gaps, "seconds": round(took, 1),
        **{k: ev[k] for k in FIGURES},
    }  # fmt: skip


def summarise(scenario: str, runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Median and worst of each figure over the seeds."""
    row: dict[str, Any] = {"scenario": scenario, "seeds": len(runs)}
    for key in FIGURES:
        values = np.array([r[key] for r in runs], dtype=float)
        row[f"{key}_median"] = round(float(np.median(values)), 4)
        row[f"{key}_worst"] = round(float(np.max(values)), 4)
    row["map_better_than_dr"] = sum(r["ape_rmse"] < r["odometry_ape_rmse"] for r in runs)
    row["loop_closures_median"] = float(np.median([r["loop_closures"] for r in runs]))
    return row


def main() -> int:
    """Run every scenario and seed; print a table and the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--rows", default=",".join(ROWS))
    parser.add_argument("--preset", default="poseidon-lvc")
    args = parser.parse_args()
    rows, every = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for scenario in args.rows.split(","):
            runs = []
            for seed in range(args.seeds):
                runs.append(one(scenario, seed, args.preset, Path(tmp)))
                r = runs[-1]
                print(f"{scenario} seed {seed}: map APE {r['ape_rmse']:.3f} m (z {r['ape_z_rmse']:.3f}), "
                      f"DR {r['odometry_ape_rmse']:.3f} m (z {r['odometry_ape_z_rmse']:.3f}), "
                      f"{r['loop_closures']} loop closures, {r['dvl_gaps']} DVL gaps", file=sys.stderr)  # fmt: skip
            rows.append(summarise(scenario, runs))
            every[scenario] = runs
    print(json.dumps({"preset": args.preset, "rows": rows, "runs": every}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

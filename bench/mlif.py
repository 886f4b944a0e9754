"""PC-MLIF against the CAN pose cells on simulated logs: APE and frames/s (``pc_model = mlif`` vs ``can``).

Usage: python bench/mlif.py [--scenario loop] [--seeds 0,1,2] [--preset circle] [--work DIR]

For each seed: ``mapserver simulate SCENARIO --seed S``, then for each pose-cell model
``mapserver process LOG --preset P --set pc_model=M --out m.json --json`` and
``mapserver evaluate m.json --ground-truth GT --json``, in subprocesses with one BLAS/OpenMP/torch thread
(``OMP_NUM_THREADS=1``: the MLIF networks' small tensors run several times slower with threads fighting
for the cores, and a thread count changes no bit of the map). frames/s is frames over the process
command's own figure (``frames_per_s`` of its JSON: the log read and the engine, not interpreter start).
Sessions of multi-session scenarios (``cave3d``) are processed one by one, each evaluated against its own
ground truth. The last line of stdout is one JSON object: per model the APE RMSE (experiences, metres) and
frames/s per run, their median and worst, and the runs themselves.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

MODELS = ("can", "mlif")


def _run(args: list[str]) -> dict[str, object]:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    cli = "import sys; from mapserver.cli import main; sys.exit(main(sys.argv[1:]))"
    done = subprocess.run([sys.executable, "-c", cli, *args, "--json"], capture_output=True, text=True, env=env,
                          check=True)
    result: dict[str, object] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


def _one_seed(scenario: str, seed: int, preset: str, work: Path) -> list[dict[str, object]]:
    """Simulate one seed, process every session with both models, and evaluate each map."""
    out = work / f"{scenario}-{seed}"
    sim = _run(["simulate", scenario, "--out", str(out), "--seed", str(seed)])
    rows = []
    for session in sim["sessions"]:  # type: ignore[attr-defined]
        for model in MODELS:
            m = out / f"{session['name']}-{model}.json"
            processed = _run(["process", str(out / session["log"]), "--preset", preset,
                              "--set", f"pc_model={model}", "--out", str(m)])
            ev = _run(["evaluate", str(m), "--ground-truth", str(out / session["ground_truth"])])
            rows.append({"seed": seed, "session": session["name"], "model": model, "ape_rmse": ev["ape_rmse"],
                         "odometry_ape_rmse": ev["odometry_ape_rmse"], "frames": session["frames"],
                         "frames_per_s": processed["frames_per_s"],
                         "experiences": ev["experiences"]})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="loop")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--preset", default="circle")
    parser.add_argument("--work", default=None, help="keep the logs and maps here (default: a temporary folder)")
    args = parser.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work or tmp)
        rows = [row for seed in seeds for row in _one_seed(args.scenario, seed, args.preset, work)]
    summary: dict[str, object] = {"scenario": args.scenario, "preset": args.preset, "seeds": seeds}
    for model in MODELS:
        ape = [float(r["ape_rmse"]) for r in rows if r["model"] == model]  # type: ignore[arg-type]
        fps = [float(r["frames_per_s"]) for r in rows if r["model"] == model]  # type: ignore[arg-type]
        summary[model] = {"ape_rmse_median": statistics.median(ape), "ape_rmse_worst": max(ape),
                          "frames_per_s_median": statistics.median(fps), "frames_per_s_worst": min(fps)}
    summary["runs"] = rows
    print(json.dumps(summary))


if __name__ == "__main__":
    main()

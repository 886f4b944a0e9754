"""End-to-end `mapserver process --db` throughput of a scenario's two sessions: alone, then merging.

Usage: python bench/process_throughput.py [--scenario cave3d] [--preset poseidon] [--seed 0] [--repeat 5]
       [--set K=V,...]

Simulates the scenario once, then ``--repeat`` times: session 1 into a new SQLite database, and session 2
into a copy of that database (it is matched against session 1's map and merges when the views say so). Each
run is its own ``mapserver process --json`` program, as a user runs it, so the figure includes what the
command's clock includes (opening the log and the database, the frames, the merge, storing), not the
program's start. Prints each run's ``frames_per_s`` and, per session, the median, min and max; the runs
alternate, so a busy machine slows both alike. Last stdout line: one JSON object
{"scenario", "preset", "session1_fps": [...], "session2_fps": [...], "merges"}.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ENTRY = "import sys; from mapserver.cli import entry; sys.argv[0] = 'mapserver'; sys.exit(entry())"
CLI = [sys.executable, "-c", ENTRY]


def _process(log: Path, db: Path, preset: str, settings: str | None) -> dict:
    """Run ``mapserver process LOG --db sqlite:///DB --json`` and return its summary."""
    command = [*CLI, "process", str(log), "--preset", preset, "--db", f"sqlite:///{db}", "--json"]
    if settings:
        command += ["--set", settings]
    done = subprocess.run(command, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    """Simulate, process both sessions ``--repeat`` times, print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="cave3d")
    parser.add_argument("--preset", default="poseidon")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--set", dest="settings", default=None, help="engine settings, as process --set")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        subprocess.run([*CLI, "simulate", args.scenario, "--out", str(root / "logs"), "--seed", str(args.seed)],
                       capture_output=True, check=True)  # fmt: skip
        info = json.loads((root / "logs" / "scenario.json").read_text())
        first, second = (root / "logs" / s["log"] for s in info["sessions"][:2])
        fps: dict[str, list[float]] = {"session1": [], "session2": []}
        merges: list[list[str]] = []
        for n in range(args.repeat):
            alone, merged = root / f"alone{n}.db", root / f"merged{n}.db"
            one = _process(first, alone, args.preset, args.settings)
            shutil.copyfile(alone, merged)
            two = _process(second, merged, args.preset, args.settings)
            fps["session1"].append(one["frames_per_s"])
            fps["session2"].append(two["frames_per_s"])
            merges.append([f"{m.get('frame')}:{m.get('status')}" for m in two["merges"]])
            print(f"run {n}: session 1 {one['frames_per_s']} frames/s, session 2 {two['frames_per_s']} frames/s "
                  f"(merges {merges[-1]})")  # fmt: skip
    for name, values in fps.items():
        print(f"{name}: median {statistics.median(values):.1f} frames/s (min {min(values)}, max {max(values)})")
    print(json.dumps({"scenario": args.scenario, "preset": args.preset, "session1_fps": fps["session1"],
                      "session2_fps": fps["session2"], "merges": merges}))  # fmt: skip


if __name__ == "__main__":
    main()

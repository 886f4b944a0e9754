"""Offline merge search time: ``find_match`` of a map of N templates against a map of N templates.

Usage: python bench/find_match.py [--templates 20000] [--sample 200] [--seed 0]

``find_match`` (``mapserver merge``) matches every template of map A, in creation order, against all of
map B's with the engine's matcher (``LocalViewCells.match`` with the match threshold as its limit). Its
cost is one vectorised match per A template: O(N_A · N_B). This script renders real ``circle`` templates
(the ``loop`` scenario at scale 2, one lap), makes a B of ``--templates`` distinct views from them (each
rendered view also turned by multiples of 13 template columns, more than the matcher's ±5-column search,
so no two are the same view), times ``--sample`` A templates against B on one core and extrapolates to
N_A = N_B. The last line of stdout is one JSON object:
{"templates", "per_template_s", "find_match_s_estimate"}.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from core import Engine, preset
from core.localview import LocalViewCells
from mapserver.ingest import open_log
from mapserver.ingest.simulator import simulate


def real_templates(seed: int) -> np.ndarray:
    """Return the templates of one simulated lap (circle preset)."""
    params = preset("circle")
    with tempfile.TemporaryDirectory() as folder:
        info = simulate("loop", folder, seed=seed, scale=2.0, params={"laps": 1.0})
        engine = Engine(params)
        with open_log(Path(folder) / info["single"]["log"]) as log:
            for frame in log.frames():
                engine.step(frame.image, frame.motion, frame.stamp_ns * 1e-9)
    return np.asarray(engine.snapshot()["lv_templates"], dtype=np.float32)


def main() -> None:
    """Run the benchmark and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--templates", type=int, default=20000)
    parser.add_argument("--sample", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    params = preset("circle")
    base = real_templates(args.seed)
    turns = -(-args.templates // base.shape[0])
    b = np.concatenate([np.roll(base, 13 * k, axis=2) for k in range(turns)])[: args.templates]
    queries = real_templates(args.seed + 1)[: args.sample]
    cells = LocalViewCells(params)
    cells.add_templates(b, b.reshape(b.shape[0], -1).mean(axis=1, dtype=np.float64))
    started = time.perf_counter()
    for q in queries:
        cells.match(q, float(q.mean(dtype=np.float64)), limit=params.vt_match_threshold)
    per = (time.perf_counter() - started) / queries.shape[0]
    estimate = per * args.templates
    print(f"{b.shape[0]} stored templates: {per * 1e3:.1f} ms per A template → find_match of {args.templates} "
          f"× {args.templates} templates ≈ {estimate:.0f} s on one core")  # fmt: skip
    print(json.dumps({"templates": args.templates, "per_template_s": round(per, 5),
                      "find_match_s_estimate": round(estimate, 1)}))  # fmt: skip


if __name__ == "__main__":
    main()

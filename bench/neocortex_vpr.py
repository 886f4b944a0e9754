"""Issue 17 figures: place recognition of the ``lvc`` and ``sdr-htm`` front-ends, VPR Guard on and off.

Usage: python bench/neocortex_vpr.py [--out DIR] [--seed 0 | --seeds 0,1,2] [--scale 1.0]
       [--scenarios aliased,cave3d] [--frontends lvc,sdr-htm,sdr-htm-imin8,sdr-htm+sonar]
       [--sim sonar=1,turbidity=3] [--guards on,off] [--reuse]

For each scenario the simulator writes its logs (all sessions, then the single run when there is one);
every session log of a scenario goes through ONE engine in turn (so a later session's look-alike places
meet the earlier sessions' view cells) with the scenario's preset and its variants:

* ``lvc``: the preset with intensity templates (``cave3d``: ``poseidon-lvc``, the preset's own LVC values);
* ``sdr-htm``: the preset with ``frontend = "sdr-htm"`` (weight-free encoder, thesis HTM values; ``cave3d``:
  ``poseidon``'s values, 16×6 encoder input, I_min 8, VPR Guard at 2 repeats);
* ``sdr-htm-imin8`` (on request): ``sdr-htm`` with the intersection gate lowered from 12 to 8 of 15 bits;
* ``sdr-sp``, ``sdr-sp-imin8`` (on request): the descriptor from the SP's columns instead of the TM's
  winner cells (``sv_descriptor_source = "sp"``): the same pipeline without sequence memory;

A variant may add parameters after ``@`` (``;``-separated), e.g.
``sdr-sp@sv_min_intersection=6;sv_enable_f1_gate=0``: the same pipeline at other gates, for a
precision-recall sweep (quote the list in a shell). A variant with ``+sonar`` also reads the log's sonar
topic (``--sim sonar=1`` makes ``cave3d`` write one;
``turbidity=T`` fogs its camera) as the front-end's second modality (Eq. 4.3, OR fusion). Each runs with
``vpr_guard`` on and off (``--guards``). Per run it prints the place-recognition rates of
:func:`mapserver.evaluation.place_recognition` (recall = revisit_match_rate; precision = 1 −
false_match_rate, with the evaluation's default radii), the loop-closure links judged against the ground
truth (TP when the two experiences' true positions are within 5 m, the thesis's d_thr), the counts, and
the front-end throughput (frames/s of the whole engine). With ``--seeds`` every scenario is simulated
once per seed and each variant's counts are summed over the seeds (recall and precision of the sums;
printed as ``total/...`` keys). The last stdout line is one JSON object.
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

from core.config import preset
from core.engine import Engine
from core.experience_map import LinkKind
from mapserver.evaluation import interpolate_poses, place_recognition
from mapserver.formats import Trajectory, read_tum
from mapserver.ingest.simulator.output import simulate
from mapserver.params import with_settings
from mapserver.processing.pipeline import run_engine

D_THR = 5.0
VARIANTS: dict[str, dict[str, Any]] = {
    "lvc": {"frontend": "lvc"},
    "sdr-htm": {"frontend": "sdr-htm"},
    "sdr-htm-imin8": {"frontend": "sdr-htm", "sv_min_intersection": 8},
    "sdr-sp": {"frontend": "sdr-htm", "sv_descriptor_source": "sp"},
    "sdr-sp-imin8": {"frontend": "sdr-htm", "sv_descriptor_source": "sp", "sv_min_intersection": 8},
}


LVC_PRESET = {"poseidon": "poseidon-lvc"}
"""A scenario preset whose front-end is ``sdr-htm``, and the preset of its intensity-template values."""


def _ground_truth(directory: Path, logs: list[dict[str, Any]]) -> Trajectory:
    parts = [read_tum(directory / s["ground_truth"]) for s in logs]
    return Trajectory(
        np.concatenate([p.stamps_s for p in parts]),
        np.concatenate([p.positions_xyz for p in parts]),
        np.concatenate([p.quat_xyzw for p in parts]),
    )


def _loop_links(engine: Engine, gt: Trajectory) -> dict[str, int]:
    snap = engine.snapshot()
    kinds = snap["em_link_kind"].astype(np.int64)
    src, dst = snap["em_link_from"][kinds == LinkKind.LOOP], snap["em_link_to"][kinds == LinkKind.LOOP]
    stamps = snap["em_stamp"]
    a = interpolate_poses(gt, stamps[src], max_diff_s=0.5)
    b = interpolate_poses(gt, stamps[dst], max_diff_s=0.5)
    d = np.linalg.norm(a[:, :3] - b[:, :3], axis=1)
    return {"loop_links": int(src.size), "tp": int(np.sum(d <= D_THR)), "fp": int(np.sum(d > D_THR))}


def _run(
    directory: Path, logs: list[dict[str, Any]], params: Any, gt: Trajectory, topics: dict[str, str] | None = None
) -> dict[str, Any]:
    engine = Engine(params)
    rows: list[tuple[float, int, int]] = []

    def record(frame: Any, result: Any) -> None:
        rows.append((frame.stamp_ns * 1e-9, int(result.template), int(result.template_created)))

    started = time.perf_counter()
    frames = 0
    for s in logs:
        frames += run_engine(engine, directory / s["log"], topics=topics, on_step=record).frames
    seconds = time.perf_counter() - started
    pr = place_recognition(rows, gt)
    false_rate = pr["false_match_rate"]
    return {
        "frames": frames,
        "view_cells": engine.template_count,
        "experiences": engine.experience_count,
        "recall": pr["revisit_match_rate"],
        "precision": None if false_rate is None else 1.0 - false_rate,
        "revisit_frames": pr["revisit_frames"],
        "revisit_matched": pr["revisit_matched"],
        "matched_frames": pr["matched_frames"],
        "false_matches": pr["false_matches"],
        **_loop_links(engine, gt),
        "frames_per_s": round(frames / seconds, 1),
        "ms_per_frame": round(1000 * seconds / frames, 2),
    }


COUNTS = ("revisit_frames", "revisit_matched", "matched_frames", "false_matches", "loop_links", "tp", "fp",
          "view_cells", "experiences", "frames")


def _totals(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Return the counts of several seeds' runs summed, with recall and precision of the sums."""
    total = {key: int(sum(r[key] for r in runs)) for key in COUNTS}
    total["recall"] = total["revisit_matched"] / total["revisit_frames"] if total["revisit_frames"] else None
    total["precision"] = 1.0 - total["false_matches"] / total["matched_frames"] if total["matched_frames"] else None
    total["seeds"] = len(runs)
    return total


def main() -> None:
    """Simulate, run every variant and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--seeds", default="", help="several simulator seeds, e.g. 0,1,2 (counts summed)")
    parser.add_argument("--scale", type=float, default=1.0)
    parser.add_argument("--scenarios", default="aliased,cave3d")
    parser.add_argument("--frontends", default="lvc,sdr-htm")
    parser.add_argument("--sim", default="", help="simulator parameters, e.g. sonar=1,turbidity=3")
    parser.add_argument("--guards", default="on,off")
    parser.add_argument("--reuse", action="store_true", help="use the logs already simulated in --out")
    args = parser.parse_args()
    sim = {k: float(v) for k, v in (item.split("=", 1) for item in filter(None, args.sim.split(",")))}
    out = args.out or Path(tempfile.mkdtemp(prefix="neocortex-vpr-"))
    figures: dict[str, Any] = {}
    seeds = [int(x) for x in args.seeds.split(",")] if args.seeds else [args.seed]
    for seed in seeds:
        for name in args.scenarios.split(","):
            directory = out / (name if len(seeds) == 1 else f"{name}-{seed}")
            if args.reuse and (directory / "scenario.json").is_file():
                info = json.loads((directory / "scenario.json").read_text(encoding="utf-8"))
            else:
                info = simulate(name, directory, seed=seed, scale=args.scale, params=sim or None)
            logs = list(info["sessions"]) + ([info["single"]] if info.get("single") else [])
            gt = _ground_truth(directory, logs)
            for variant in args.frontends.split(","):
                front, _, extra = variant.partition("+")
                front, _, given = front.partition("@")
                lvc = LVC_PRESET.get(info["preset"]) if VARIANTS[front]["frontend"] == "lvc" else None
                base = preset(lvc or info["preset"])
                params = with_settings(base.replace(**VARIANTS[front]), given.replace(";", ","))  # process --set's
                topics = {"sonar": info["sonar"]["topic"]} if extra == "sonar" else None
                for guard in (g == "on" for g in args.guards.split(",")):
                    key = f"{name}/{variant}/guard-{'on' if guard else 'off'}"
                    key = key if len(seeds) == 1 else f"{key}/seed-{seed}"
                    figures[key] = _run(directory, logs, params.replace(vpr_guard=guard), gt, topics)
                    print(key, json.dumps(figures[key]), flush=True)
    if len(seeds) > 1:
        for key in sorted({k.rsplit("/seed-", 1)[0] for k in figures}):
            figures[f"total/{key}"] = _totals([v for k, v in figures.items() if k.rsplit("/seed-", 1)[0] == key])
            print(f"total/{key}", json.dumps(figures[f"total/{key}"]), flush=True)
    print(json.dumps(figures))


if __name__ == "__main__":
    main()

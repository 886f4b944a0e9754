"""Engine throughput: frames per second with the template store pre-filled to a given size.

Usage: python bench/core_throughput.py --preset irat --templates 1000 [--frames 1500]

Pre-fills the engine with N templates (and one experience chain of N experiences,
one pose-cell link per template), then feeds synthetic camera frames of a textured
corridor revisited every lap, with odometry, through ``Engine.step`` on one core
(BLAS threads pinned to 1). The pre-filled templates are per-pixel noise around a
level: the hardest case for the matcher's early break (real, spatially smooth
templates are pruned sooner), so the figure is conservative. frames_per_s covers
``Engine.step`` only; the end-of-log ``settle()`` is timed separately.
The last line of stdout is one JSON object:
{"preset", "templates", "experiences", "frames_per_s"}.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import numpy as np

from core import Engine, Motion, preset


def corridor_frames(n: int, height: int, width: int, seed: int = 0):
    """Yield (image, motion, stamp): a smooth random texture strip viewed along a 60 m loop."""
    rng = np.random.default_rng(seed)
    px_per_m = 10
    columns = 60 * px_per_m
    base = rng.random((height, columns))
    kernel = np.ones(9) / 9.0
    smooth = np.stack([np.convolve(np.concatenate([r[-4:], r, r[:4]]), kernel, "valid") for r in base])
    brightness = np.linspace(0.6, 1.4, columns)[None, :]  # places differ in mean intensity as real scenes do
    texture = np.clip(255 * smooth * brightness, 0, 255).astype(np.uint8)
    dt = 0.1
    speed = 1.0
    dyaw = speed * dt / (60 / (2 * math.pi))
    for i in range(n):
        start = int(i * speed * dt * px_per_m) % columns
        idx = (start + np.arange(width)) % columns
        motion = Motion(speed * dt, 0.0, 0.0, dyaw, dt) if i else Motion(0.0, 0.0, 0.0, 0.0, 0.0)
        yield texture[:, idx], motion, i * dt


def prefill(engine: Engine, n: int, seed: int = 1) -> None:
    """Add n templates (means spread like real views), their links and an experience chain."""
    if n <= 0:
        return
    p = engine.params
    rng = np.random.default_rng(seed)
    ty, tx = p.template_y_size, p.template_x_size
    levels = rng.uniform(0.15, 0.85, size=(n, 1, 1))
    templates = np.clip(levels + rng.normal(0, 0.08, size=(n, ty, tx)), 0, 1).astype(np.float32)
    engine.local_view.add_templates(templates, templates.reshape(n, -1).mean(axis=1).astype(np.float64))
    engine.lv_origin.extend([0] * n)
    dims = np.asarray(engine.pose_cells.shape, dtype=np.float64)
    coords = rng.uniform(0, 1, size=(n, len(dims))) * dims
    for i in range(n):
        engine.pose_cells.add_link(i, coords[i])
    em = engine.map
    for i in range(n):
        em.on_odo(Motion(0.5, 0.0, 0.0, 0.01, 0.5))
        em.create_experience(i, coords[i], 0.5 * i, 0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="irat")
    parser.add_argument("--templates", type=int, default=1000)
    parser.add_argument("--frames", type=int, default=1500)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    args = parser.parse_args()
    params = preset(args.preset)
    engine = Engine(params)
    prefill(engine, args.templates)
    frames = list(corridor_frames(args.frames + 200, args.height, args.width))
    for img, motion, stamp in frames[:200]:  # warm-up
        engine.step(img, motion, stamp)
    start = time.perf_counter()
    cpu_start = time.process_time()
    for img, motion, stamp in frames[200:]:
        engine.step(img, motion, stamp)
    elapsed = time.perf_counter() - start
    cpu = time.process_time() - cpu_start
    fps = args.frames / elapsed
    settle_start = time.perf_counter()
    engine.settle()
    settle_s = time.perf_counter() - settle_start
    print(
        f"{args.preset}: {args.frames} frames in {elapsed:.3f} s with {engine.template_count} templates, "
        f"{engine.experience_count} experiences, {engine.loop_closures} loop closures; "
        f"end-of-log settle() {settle_s * 1000:.0f} ms (not in frames_per_s); "
        f"{args.frames / cpu:.1f} frames per CPU-second (wall clock suffers when other work shares the cores)"
    )
    print(
        json.dumps(
            {
                "preset": args.preset,
                "templates": engine.template_count,
                "experiences": engine.experience_count,
                "frames_per_s": round(fps, 1),
            }
        )
    )


if __name__ == "__main__":
    main()

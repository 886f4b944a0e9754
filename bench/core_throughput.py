"""Engine throughput: frames per second with the template store pre-filled to a given size.

Usage: python bench/core_throughput.py --preset irat --templates 1000 [--frames 1500]

Pre-fills the engine with N view cells (and one experience chain of N experiences,
one pose-cell link per view cell), then feeds synthetic camera frames of a textured
corridor revisited every lap, with odometry, through ``Engine.step`` on one core
(BLAS threads pinned to 1). Any preset: for the ``lvc`` front-end the pre-filled
templates are per-pixel noise around a level: the hardest case for the matcher's early
break (real, spatially smooth templates are pruned sooner), so the figure is conservative;
for ``sdr-htm`` (``poseidon``, ``neoslam``) they are prototypes of random cell ids with
random LSBH codes (every prototype is scored on every frame, so only their number matters). frames_per_s covers
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
from collections.abc import Iterator

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import numpy as np

from core import Engine, Motion, Params, preset
from core.localview import LocalViewCells
from core.neocortex import NeocortexViewCells


def corridor_frames(n: int, height: int, width: int, seed: int = 0) -> Iterator[tuple[np.ndarray, Motion, float]]:
    """Yield (image, motion, stamp): a smooth random texture strip viewed along a loop.

    The loop is 60 m (600 columns at 10 px/m), or two image widths when the image is wider than 300 px.
    """
    rng = np.random.default_rng(seed)
    px_per_m = 10
    columns = max(60 * px_per_m, 2 * width)
    loop_m = columns / px_per_m
    base = rng.random((height, columns))
    kernel = np.ones(9) / 9.0
    smooth = np.stack([np.convolve(np.concatenate([r[-4:], r, r[:4]]), kernel, "valid") for r in base])
    brightness = np.linspace(0.6, 1.4, columns)[None, :]  # places differ in mean intensity as real scenes do
    texture = np.clip(255 * smooth * brightness, 0, 255).astype(np.uint8)
    dt = 0.1
    speed = 1.0
    dyaw = speed * dt / (loop_m / (2 * math.pi))
    for i in range(n):
        start = int(i * speed * dt * px_per_m) % columns
        idx = (start + np.arange(width)) % columns
        motion = Motion(speed * dt, 0.0, 0.0, dyaw, dt) if i else Motion(0.0, 0.0, 0.0, 0.0, 0.0)
        yield texture[:, idx], motion, i * dt


def prefill(engine: Engine, n: int, seed: int = 1) -> None:
    """Add n view cells (:func:`prefill_views`), their pose-cell links and an experience chain of n experiences."""
    if n <= 0:
        return
    rng = np.random.default_rng(seed)
    prefill_views(engine.local_view, n, rng)
    engine.lv_origin.extend([0] * n)
    engine.lv_place.extend([-1] * n)  # no place: as templates of a snapshot made before the keys
    engine.lv_place_offset.extend(np.zeros((n, 4)))
    engine.lv_place_yaw.extend([math.nan] * n)
    dims = np.asarray(engine.pose_cells.shape, dtype=np.float64)
    coords = rng.uniform(0, 1, size=(n, len(dims))) * dims
    for i in range(n):
        engine.pose_cells.add_link(i, coords[i])
    em = engine.map
    for i in range(n):
        em.on_odo(Motion(0.5, 0.0, 0.0, 0.01, 0.5))
        em.create_experience(i, coords[i], 0.5 * i, 0)


def prefill_views(view_cells: LocalViewCells | NeocortexViewCells, n: int, rng: np.random.Generator) -> None:
    """Add n view cells to either front-end through its public store method.

    ``lvc``: intensity templates of per-pixel noise around a level, means spread like real views
    (:meth:`LocalViewCells.add_templates`). ``sdr-htm``: prototypes of ``sv_tm_topk`` distinct random
    cell ids, each with the packed code of a random LSBH SDR (2k of L bits;
    :meth:`NeocortexViewCells.add_prototypes`).
    """
    p = view_cells.params
    if isinstance(view_cells, NeocortexViewCells):
        cells = view_cells.tm.cells
        topk = p.sv_tm_topk
        prototypes = np.sort(np.stack([rng.choice(cells, size=topk, replace=False) for _ in range(n)]), axis=1)
        half = p.lsbh_bits // 2
        ranks = np.argsort(rng.normal(size=(n, half)), axis=1)
        bits = np.zeros((n, 2 * half), dtype=bool)
        rows = np.arange(n)[:, None]
        bits[rows, ranks[:, -view_cells.k :]] = True  # top k
        bits[rows, half + ranks[:, : view_cells.k]] = True  # bottom k
        view_cells.add_prototypes(prototypes, np.full(n, topk), np.packbits(bits, axis=1))
        return
    ty, tx = p.template_y_size, p.template_x_size
    levels = rng.uniform(0.15, 0.85, size=(n, 1, 1))
    templates = np.clip(levels + rng.normal(0, 0.08, size=(n, ty, tx)), 0, 1).astype(np.float32)
    view_cells.add_templates(templates, templates.reshape(n, -1).mean(axis=1).astype(np.float64))


def image_size(params: Params, width: int | None, height: int | None) -> tuple[int, int]:
    """Return (width, height) of the bench's images: as given, else 160 × 120.

    A side whose crop would keep fewer pixels than the template has cells (``stlucia``, ``lake``: rows 150..300)
    is widened to the crop's far edge.
    """
    p = params
    return (
        _side(width, 160, p.image_crop_x_min, p.image_crop_x_max, p.template_x_size),
        _side(height, 120, p.image_crop_y_min, p.image_crop_y_max, p.template_y_size),
    )


def _side(given: int | None, default: int, low: int, high: int, cells: int) -> int:
    """Return ``given``, else ``default`` if crop ``low..high`` (−1: the end) keeps ``cells`` pixels, else ``high``."""
    if given is not None:
        return given
    kept = (default if high < 0 else min(high, default)) - min(low, default)
    return default if kept >= cells else max(default, high)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="irat")
    parser.add_argument("--templates", type=int, default=1000)
    parser.add_argument("--frames", type=int, default=1500)
    parser.add_argument("--width", type=int, help="image width (default: 160, or the crop's far edge if needed)")
    parser.add_argument("--height", type=int, help="image height (default: 120, or the crop's far edge if needed)")
    args = parser.parse_args()
    params = preset(args.preset)
    engine = Engine(params)
    prefill(engine, args.templates)
    width, height = image_size(params, args.width, args.height)
    frames = list(corridor_frames(args.frames + 200, height, width))
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

"""Merge time: a partial map merged into a large stored map (mapserver.merge, online path).

Usage: python bench/merge.py [--preset circle] [--experiences 100000] [--templates 20000]
       [--links 200000] [--partial-experiences 10000] [--partial-templates 2000] [--repeat 3]

Builds two synthetic engine snapshots (vectorised, seeded): a stored map with the given
numbers of experiences, templates (one pose-cell link each) and experience links (an
odometry chain plus loop closures), and a partial map; then times, on one core, the steps
the online driver runs when a merge is confirmed:

* ``merge_states`` on the snapshots (operations i–iv, the whole algorithm);
* ``merge_engine`` end to end (partial ``snapshot()``, the merge, and the merged engine, which keeps the
  stored map's templates array itself);
* ``restore_merged``: ``Engine.restore`` of the merged snapshot (the engine the session
  continues in), relaxation scheduled at the merge links;
* the first frame's bounded share of relaxation after it (``relax_step``).

The restore is timed last, from one merged snapshot, after the synthetic maps and the partial engine are
dropped (nothing of the restore needs them). Figures are the best of ``--repeat`` runs (``*_first_s``: the
first run); ``peak_rss_mb`` is the process's peak resident memory, the synthetic maps included. The last
line of stdout is one JSON object:
{"preset", "stored_experiences", "stored_templates", "stored_links", "partial_experiences",
 "merge_states_s", "restore_s", "restore_first_s", "relax_step_s", "merge_engine_s", "merge_engine_first_s",
 "peak_rss_mb", "target_s", "within_target"}.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time
from collections.abc import Callable

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import numpy as np

from core import Engine, Params, preset
from core.angles import wrap_angle_below_pi
from core.se3 import relative
from mapserver.merge import Match, MergeRecord, StoredMap, merge_engine, merge_states, restore_merged
from mapserver.merge.lattice import splat

TARGET_S = 1.0


def synthetic_state(
    params: Params, experiences: int, templates: int, links: int, origin: int, seed: int
) -> dict[str, np.ndarray]:
    """Return a consistent snapshot: a random-walk route, templates in creation order, loops closed."""
    rng = np.random.default_rng(seed)
    dims = np.asarray(params.lattice_shape, dtype=np.float64)
    rank = dims.size
    steps = np.column_stack(
        [rng.uniform(0.5, 1.5, experiences), rng.normal(0, 0.05, experiences), rng.normal(0, 0.02, experiences),
         rng.normal(0, 0.1, experiences)]
    )
    yaw = np.cumsum(steps[:, 3])
    pose = np.column_stack(
        [np.cumsum(steps[:, 0] * np.cos(yaw)), np.cumsum(steps[:, 0] * np.sin(yaw)), np.cumsum(steps[:, 2]),
         wrap_angle_below_pi(yaw)]
    )
    exp_template = (np.arange(experiences) * templates) // experiences
    pcs = rng.uniform(0, 1, size=(experiences, rank)) * dims
    first_of_template = np.searchsorted(exp_template, np.arange(templates))
    ty, tx = params.template_y_size, params.template_x_size
    views = np.empty((templates, ty, tx), dtype=np.float32)
    for first in range(0, templates, 1024):  # one (templates, ty, tx) draw's values, 1024 rows of float64 at a time
        views[first : first + 1024] = rng.uniform(0, 1, size=(min(1024, templates - first), ty, tx))
    chain = np.arange(experiences - 1)
    loops = links - chain.size
    loop_from = rng.integers(0, experiences, loops)
    loop_to = np.clip(loop_from + rng.integers(2, 50, loops), 0, experiences - 1)
    src = np.concatenate([chain, loop_from])
    dst = np.concatenate([chain + 1, loop_to])
    transform = relative(pose[src], pose[dst])
    kind = np.concatenate([np.zeros(chain.size, dtype=np.int8), np.ones(loops, dtype=np.int8)])
    accum = np.zeros(6)
    accum[3] = pose[-1, 3]
    history = np.full(params.vpr_window, -1, dtype=np.int64)
    return {
        "lv_templates": views,
        "lv_means": views.reshape(templates, -1).mean(axis=1).astype(np.float64),
        "lv_origin": np.full(templates, origin, dtype=np.int64),
        "lv_current": np.asarray(templates - 1, dtype=np.int64),
        "lv_previous": np.asarray(templates - 2, dtype=np.int64),
        "lv_relative_rad": np.asarray(0.0),
        "vo_prev_vtrans": np.zeros(0),
        "vo_prev_vrot": np.zeros(0),
        "pc_activity": splat(tuple(int(d) for d in dims), pcs[-1]),
        "pc_best": pcs[-1].copy(),
        "pc_link_template": np.arange(templates, dtype=np.int64),
        "pc_link_coords": pcs[first_of_template].copy(),
        "pc_link_strength": np.ones(templates),
        "pc_link_decay": np.full(templates, params.vt_active_decay),
        "pc_current_vt": np.asarray(templates - 1, dtype=np.int64),
        "pc_prev_vt": np.asarray(templates - 2, dtype=np.int64),
        "pc_vt_delta_th": np.asarray(0.0),
        "em_pose": pose,
        "em_pc": pcs,
        "em_template": exp_template.astype(np.int64),
        "em_stamp": np.arange(experiences, dtype=np.float64),
        "em_origin": np.full(experiences, origin, dtype=np.int64),
        "em_link_from": src.astype(np.int64),
        "em_link_to": dst.astype(np.int64),
        "em_link_transform": transform,
        "em_link_dt": np.ones(src.size),
        "em_link_distance": np.linalg.norm(transform[:, :3], axis=1),
        "em_link_kind": kind,
        "em_current": np.asarray(experiences - 1, dtype=np.int64),
        "em_previous": np.asarray(experiences - 2, dtype=np.int64),
        "em_accum": accum,
        "em_relax_pending": np.asarray(False),
        "gate_history": history,
        "gate_state": np.zeros(3),
        "eng_frames": np.asarray(experiences * 2, dtype=np.int64),
        "eng_last_stamp": np.asarray(float(experiences)),
    }


def best_of(repeat: int, fn: Callable[[], object]) -> tuple[float, float]:
    """Return (the shortest, the first) wall time of ``repeat`` calls of ``fn`` (each result dropped at once)."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times), times[0]


def time_merges(
    params: Params, args: argparse.Namespace
) -> tuple[tuple[float, float, float], tuple[dict[str, np.ndarray], MergeRecord]]:
    """Build the two maps; return the seconds of merge_states and merge_engine (best, first), and one merged snapshot.

    The synthetic maps, the partial engine and every merged engine are dropped on return: the merged snapshot
    and its record are all that is left for :func:`time_restore`.
    """
    loaded = synthetic_state(params, args.experiences, args.templates, args.links, origin=1, seed=1)
    partial_links = max(args.partial_experiences - 1, int(1.5 * args.partial_experiences))
    partial = synthetic_state(
        params, args.partial_experiences, args.partial_templates, partial_links, origin=2, seed=2
    )
    e_u = args.experiences // 2
    u = int(loaded["em_template"][e_u])
    last = args.partial_experiences - 1
    z = int(partial["em_template"][last])
    pairs = ((z, u), (z - 1, u - 1), (z - 2, u - 2))
    match = Match.at_experience(partial, last, u, e_u, confirmations=3, pairs=pairs)
    partial_engine = Engine.restore(params, partial, origin=2)
    stored = StoredMap(1, params, loaded)
    t_states = best_of(args.repeat, lambda: merge_states(loaded, partial, match))[0]
    t_engine, t_engine_first = best_of(args.repeat, lambda: merge_engine(stored, partial_engine, match))
    return (t_states, t_engine, t_engine_first), merge_states(loaded, partial, match)


def time_restore(
    params: Params, state: dict[str, np.ndarray], record: MergeRecord, repeat: int
) -> tuple[float, float, float]:
    """Return the seconds of restore_merged (best, first) and of the first frame's relax_step after it."""
    t_restore, t_restore_first = best_of(repeat, lambda: restore_merged(params, state, record, origin=2))

    def relax_step() -> float:
        engine = restore_merged(params, state, record, origin=2)
        assert engine.experience_count == record.experiences
        start = time.perf_counter()
        engine.map.relax_step()
        return time.perf_counter() - start

    return t_restore, t_restore_first, min(relax_step() for _ in range(repeat))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="circle")
    parser.add_argument("--experiences", type=int, default=100_000)
    parser.add_argument("--templates", type=int, default=20_000)
    parser.add_argument("--links", type=int, default=200_000)
    parser.add_argument("--partial-experiences", type=int, default=10_000)
    parser.add_argument("--partial-templates", type=int, default=2_000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    params = preset(args.preset)
    (t_states, t_engine, t_engine_first), (state, record) = time_merges(params, args)
    t_restore, t_restore_first, t_relax = time_restore(params, state, record, args.repeat)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: kB
    print(
        f"{args.preset}: stored {args.experiences} experiences / {args.templates} templates / {args.links} links, "
        f"partial {args.partial_experiences} experiences / {args.partial_templates} templates"
    )
    print(f"merge_states    {t_states:.3f} s")
    print(f"restore_merged  {t_restore:.3f} s (first run {t_restore_first:.3f} s)")
    print(f"relax_step      {t_relax:.4f} s (first frame's relaxation, ≤ {params.exp_relax_batch} experiences)")
    print(f"merge_engine    {t_engine:.3f} s (snapshot + merge + merged engine; "
          f"first run {t_engine_first:.3f} s)")  # fmt: skip
    print(f"peak RSS        {peak_mb:.0f} MB (the whole process, data included)")
    print(
        json.dumps(
            {
                "preset": args.preset,
                "stored_experiences": args.experiences,
                "stored_templates": args.templates,
                "stored_links": args.links,
                "partial_experiences": args.partial_experiences,
                "merge_states_s": round(t_states, 4),
                "restore_s": round(t_restore, 4),
                "restore_first_s": round(t_restore_first, 4),
                "relax_step_s": round(t_relax, 4),
                "merge_engine_s": round(t_engine, 4),
                "merge_engine_first_s": round(t_engine_first, 4),
                "peak_rss_mb": round(peak_mb),
                "target_s": TARGET_S,
                "within_target": t_engine <= TARGET_S,
            }
        )
    )


if __name__ == "__main__":
    main()

"""Hand-built engine snapshots (docs/architecture.md schema) for merge unit tests."""

from __future__ import annotations

import numpy as np

from core.se3 import relative
from mapserver.merge.lattice import splat

TY, TX = 4, 6


def make_state(
    poses: np.ndarray,
    pcs: np.ndarray,
    dims: tuple[int, ...],
    *,
    origin: int,
    templates: np.ndarray | None = None,
    n_templates: int | None = None,
    seed: int = 0,
    accum: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Return a consistent snapshot: experiences at ``poses``/``pcs`` chained by odometry links.

    Experience i has template ``templates[i]`` (default i); every template has one pose-cell
    link at the lattice coordinates of its first experience (templates without an
    experience get a link at the last experience's coordinates). The robot is at the last
    experience (``accum`` since it, default none).
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
    pcs = np.asarray(pcs, dtype=np.float64).reshape(-1, len(dims))
    n = poses.shape[0]
    exp_templates = np.arange(n) if templates is None else np.asarray(templates, dtype=np.int64)
    count = int(exp_templates.max()) + 1 if n_templates is None else n_templates
    rng = np.random.default_rng(seed)
    views = rng.uniform(0.0, 1.0, size=(count, TY, TX)).astype(np.float32)
    link_coords = np.tile(pcs[-1], (count, 1))
    for t in range(count):
        mine = np.flatnonzero(exp_templates == t)
        if mine.size:
            link_coords[t] = pcs[mine[0]]
    src = np.arange(n - 1, dtype=np.int64)
    dst = src + 1
    transforms = relative(poses[src], poses[dst]).reshape(-1, 4)
    robot = np.zeros(6) if accum is None else np.asarray(accum, dtype=np.float64).copy()
    if accum is None:
        robot[3] = poses[-1, 3]
    history = np.full(26, -1, dtype=np.int64)
    history[-3:] = exp_templates[-1]
    last = int(exp_templates[-1])
    return {
        "lv_templates": views,
        "lv_means": views.reshape(count, -1).mean(axis=1).astype(np.float64),
        "lv_origin": np.full(count, origin, dtype=np.int64),
        "lv_current": np.asarray(last, dtype=np.int64),
        "lv_previous": np.asarray(int(exp_templates[-2]) if n > 1 else -1, dtype=np.int64),
        "lv_relative_rad": np.asarray(0.0),
        "vo_prev_vtrans": np.zeros(0),
        "vo_prev_vrot": np.zeros(0),
        "pc_activity": splat(dims, pcs[-1]),
        "pc_best": pcs[-1].copy(),
        "pc_link_template": np.arange(count, dtype=np.int64),
        "pc_link_coords": link_coords,
        "pc_link_strength": np.ones(count),
        "pc_link_decay": np.full(count, 1.0),
        "pc_current_vt": np.asarray(last, dtype=np.int64),
        "pc_prev_vt": np.asarray(int(exp_templates[-2]) if n > 1 else -1, dtype=np.int64),
        "pc_vt_delta_th": np.asarray(0.0),
        "em_pose": poses.copy(),
        "em_pc": pcs.copy(),
        "em_template": exp_templates.copy(),
        "em_stamp": np.arange(n, dtype=np.float64) + 100.0 * origin,
        "em_origin": np.full(n, origin, dtype=np.int64),
        "em_link_from": src,
        "em_link_to": dst,
        "em_link_transform": transforms,
        "em_link_dt": np.ones(n - 1),
        "em_link_distance": np.linalg.norm(transforms[:, :3], axis=1),
        "em_link_kind": np.zeros(n - 1, dtype=np.int8),
        "em_current": np.asarray(n - 1, dtype=np.int64),
        "em_previous": np.asarray(n - 2, dtype=np.int64),
        "em_accum": robot,
        "em_relax_pending": np.asarray(False),
        "gate_history": history,
        "gate_state": np.zeros(3),
        "eng_frames": np.asarray(10 * n, dtype=np.int64),
        "eng_last_stamp": np.asarray(100.0 * origin + n),
    }

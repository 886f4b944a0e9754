"""OpenRatSLAM's own map relaxation, for ``openratslam_compat`` (differential tests against its C++ core).

The default engine relaxes towards the least-squares fixed point with an anchor and a per-frame budget
(:mod:`core.relaxation`). With ``openratslam_compat`` the map instead does what OpenRatSLAM's
``ExperienceMap::iterate`` does after every topological action (Ball et al. 2013, §III-C; OpenRatSLAM2
Eq. 8): ``exp_loops`` Gauss–Seidel sweeps, visiting experiences in id order and each one's outgoing links
in creation order. A link i → j predicts j at ``p_i + d·(cos, sin)(θ_i + heading)``; both ends move by
``exp_correction`` of the miss in opposite directions; then the headings move by ``exp_correction`` of
``Δ(θ_i + facing, θ_j)``. Nothing is anchored. The angle helpers reproduce OpenRatSLAM's ``clip_rad_180``
and ``get_signed_delta_rad`` exactly (including their interval ends), so the sweep matches the C++ to
rounding.
"""

from __future__ import annotations

import math

import numpy as np

from core.angles import TWO_PI
from core.arrays import FloatArray, IntArray


def clip_rad_180(angle: float) -> float:
    """Return ``angle`` wrapped into (−π, π] by whole turns (OpenRatSLAM ``clip_rad_180``)."""
    while angle > math.pi:
        angle -= TWO_PI
    while angle <= -math.pi:
        angle += TWO_PI
    return angle


def clip_rad_360(angle: float) -> float:
    """Return ``angle`` wrapped into [0, 2π) by whole turns (OpenRatSLAM ``clip_rad_360``)."""
    while angle < 0.0:
        angle += TWO_PI
    while angle >= TWO_PI:
        angle -= TWO_PI
    return angle


def signed_delta_rad(angle1: float, angle2: float) -> float:
    """Return the signed smallest turn from ``angle1`` to ``angle2`` (OpenRatSLAM ``get_signed_delta_rad``)."""
    direction = clip_rad_180(angle2 - angle1)
    delta = abs(clip_rad_360(angle1) - clip_rad_360(angle2))
    if delta >= TWO_PI - delta:
        delta = TWO_PI - delta
    return delta if direction > 0.0 else -delta


def sweep_order(src: IntArray) -> IntArray:
    """Return link indices in OpenRatSLAM's sweep order: by source id, then by creation."""
    return np.argsort(src, kind="stable")


def iterate(
    poses: FloatArray,
    src: IntArray,
    dst: IntArray,
    transform: FloatArray,
    loops: int,
    correction: float,
) -> None:
    """Run ``loops`` OpenRatSLAM relaxation sweeps on ``poses`` (N, ≥4: x, y, ·, θ) in place.

    ``transform`` (L, ≥4) holds each link's target in its source's frame (dx, dy, ·, dθ); OpenRatSLAM's
    ``d``/``heading_rad`` are its polar form and ``facing_rad`` is dθ. Sequential by nature (each update
    sees the previous ones), so it is a plain loop over Python floats.
    """
    if loops <= 0 or src.size == 0:
        return
    order = sweep_order(src)
    links = [
        (int(src[k]), int(dst[k]), math.hypot(transform[k, 0], transform[k, 1]),
         math.atan2(transform[k, 1], transform[k, 0]), float(transform[k, 3]))
        for k in order
    ]
    xs = poses[:, 0].tolist()
    ys = poses[:, 1].tolist()
    th = poses[:, 3].tolist()
    c = correction
    cos, sin, wrap, delta = math.cos, math.sin, clip_rad_180, signed_delta_rad
    for _ in range(loops):
        for i, j, d, heading, facing in links:
            ti = th[i]
            lx = xs[i] + d * cos(ti + heading)
            ly = ys[i] + d * sin(ti + heading)
            ex = (xs[j] - lx) * c
            ey = (ys[j] - ly) * c
            xs[i] += ex
            ys[i] += ey
            xs[j] -= ex
            ys[j] -= ey
            df = delta(ti + facing, th[j]) * c
            th[i] = wrap(ti + df)
            th[j] = wrap(th[j] - df)
    poses[:, 0] = xs
    poses[:, 1] = ys
    poses[:, 3] = th

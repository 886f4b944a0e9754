"""4-DoF rigid transforms of experience poses (x, y, z, yaw): the SE(3) subgroup of rotations about z.

Experience poses are stored as rows ``(x, y, z, yaw)`` (docs/architecture.md, ``em_pose``).
A pose is also a transform: ``T_map_body`` maps body coordinates to the map frame.
The array functions broadcast over leading axes, so whole experience maps are
transformed at once (no per-experience Python loop); their headings are wrapped to (−π, π].
The ``*_step`` functions take and return plain floats (``math.cos``/``math.sin``, no numpy
overhead) for one pose or displacement at a time, and leave the heading unwrapped (their callers
wrap it as their own data needs). The yaw ↔ quaternion conversions (a rotation by yaw about z
as ``(qx, qy, qz, qw)``) are here too.

Menezes et al. (2023) Eqs. 13–14 transform the partial map's poses by a 2-D
rotation about the matched experience plus a translation; written as poses this
is ``p' = T ⊕ p`` with ``T = T_loaded ⊕ T_partial⁻¹`` (the generalisation to
x, y, z, yaw used here).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from core.angles import wrap_angle
from core.arrays import FloatArray

if TYPE_CHECKING:
    from collections.abc import Sequence


def _as_poses(poses: npt.ArrayLike) -> FloatArray:
    p = np.asarray(poses, dtype=np.float64)
    if p.shape[-1:] != (4,):
        msg = f"poses must have shape (..., 4) as (x, y, z, yaw), got {p.shape}"
        raise ValueError(msg)
    return p


def compose(a: npt.ArrayLike, b: npt.ArrayLike, turn: tuple[FloatArray, FloatArray] | None = None) -> FloatArray:
    """Return ``a ⊕ b``: the pose ``b`` (expressed in frame ``a``) in the frame ``a`` is expressed in.

    Args:
        a: poses (..., 4) x, y, z (m), yaw (rad).
        b: poses (..., 4), broadcast against ``a``.
        turn: ``(cos, sin)`` of ``a``'s yaws, where the caller has them (the same values: taken, not computed).

    Returns:
        (..., 4): translation ``a.xyz + Rz(a.yaw)·b.xyz``, yaw ``wrap(a.yaw + b.yaw)``.
    """
    pa, pb = _as_poses(a), _as_poses(b)
    c, s = (np.cos(pa[..., 3]), np.sin(pa[..., 3])) if turn is None else turn
    out = np.empty(np.broadcast_shapes(pa.shape, pb.shape), dtype=np.float64)
    out[..., 0] = pa[..., 0] + c * pb[..., 0] - s * pb[..., 1]
    out[..., 1] = pa[..., 1] + s * pb[..., 0] + c * pb[..., 1]
    out[..., 2] = pa[..., 2] + pb[..., 2]
    out[..., 3] = wrap_angle(pa[..., 3] + pb[..., 3])
    return out


def inverse(a: npt.ArrayLike) -> FloatArray:
    """Return ``a⁻¹`` (..., 4): ``a ⊕ a⁻¹ = a⁻¹ ⊕ a = identity``."""
    pa = _as_poses(a)
    c, s = np.cos(pa[..., 3]), np.sin(pa[..., 3])
    out = np.empty_like(pa)
    out[..., 0] = -(c * pa[..., 0] + s * pa[..., 1])
    out[..., 1] = -(-s * pa[..., 0] + c * pa[..., 1])
    out[..., 2] = -pa[..., 2]
    out[..., 3] = wrap_angle(-pa[..., 3])
    return out


def relative(a: npt.ArrayLike, b: npt.ArrayLike) -> FloatArray:
    """Return ``a⁻¹ ⊕ b``: pose ``b`` in the frame of ``a`` (an experience link's transform, ``from`` = a)."""
    return compose(inverse(a), b)


def alignment(loaded: npt.ArrayLike, partial: npt.ArrayLike) -> FloatArray:
    """Return ``T = T_loaded ⊕ T_partial⁻¹``, the transform taking the partial pose onto the loaded one.

    Generalises Menezes et al. Eqs. 13–14 (Δθ = θ_l − θ_p, rotation about the matched
    experience, then translation onto it) to x, y, z, yaw.
    """
    return compose(loaded, inverse(partial))


def to_matrix(pose: npt.ArrayLike) -> FloatArray:
    """Return the homogeneous 4×4 matrix (..., 4, 4) of poses (..., 4)."""
    p = _as_poses(pose)
    c, s = np.cos(p[..., 3]), np.sin(p[..., 3])
    m = np.zeros((*p.shape[:-1], 4, 4), dtype=np.float64)
    m[..., 0, 0], m[..., 0, 1], m[..., 1, 0], m[..., 1, 1] = c, -s, s, c
    m[..., 2, 2] = 1.0
    m[..., 3, 3] = 1.0
    m[..., :3, 3] = p[..., :3]
    return m


def from_matrix(matrix: npt.ArrayLike, atol: float = 1e-9) -> FloatArray:
    """Return the pose (x, y, z, yaw) of a homogeneous 4×4 matrix whose rotation is about z only.

    Raises:
        ValueError: the matrix is not 4×4, its last row is not (0, 0, 0, 1), or its rotation
            is not a rotation about z (roll or pitch, scale or shear).
    """
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape != (4, 4):
        msg = f"expected a 4×4 matrix, got shape {m.shape}"
        raise ValueError(msg)
    yaw = math.atan2(m[1, 0], m[0, 0])
    expected = to_matrix(np.array([m[0, 3], m[1, 3], m[2, 3], yaw]))
    if not np.allclose(m, expected, atol=atol):
        msg = f"matrix is not a rotation about z plus a translation: {m.tolist()!r}"
        raise ValueError(msg)
    return np.array([m[0, 3], m[1, 3], m[2, 3], float(wrap_angle(yaw))])


# ------------------------------------------------------------------------------ plain-float steps


def compose_step(pose: Sequence[float], step: Sequence[float]) -> tuple[float, float, float, float]:
    """Return ``pose ⊕ step`` of one pose (x, y, z, yaw) and a displacement in its frame, as plain floats.

    ``(x + c·dx − s·dy, y + s·dx + c·dy, z + dz, yaw + dyaw)`` with ``c, s = cos yaw, sin yaw``; the
    heading is summed, not wrapped (dead reckoning keeps the turns it has made).
    """
    x, y, z, yaw = pose[0], pose[1], pose[2], pose[3]
    dx, dy, dz, dyaw = step[0], step[1], step[2], step[3]
    c, s = math.cos(yaw), math.sin(yaw)
    return (x + c * dx - s * dy, y + s * dx + c * dy, z + dz, yaw + dyaw)


def relative_step(start: Sequence[float], end: Sequence[float]) -> tuple[float, float, float, float]:
    """Return ``start⁻¹ ⊕ end`` of two poses (x, y, z, yaw) as plain floats: ``end`` in ``start``'s frame.

    The map-frame displacement turned by −yaw of ``start``: ``(c·Δx + s·Δy, −s·Δx + c·Δy, Δz, Δyaw)``; the
    heading difference is not wrapped.
    """
    dxw, dyw = end[0] - start[0], end[1] - start[1]
    c, s = math.cos(start[3]), math.sin(start[3])
    return (c * dxw + s * dyw, -s * dxw + c * dyw, end[2] - start[2], end[3] - start[3])


def turn_step(step: Sequence[float], yaw: float) -> tuple[float, float, float, float]:
    """Return a displacement (dx, dy, dz, dyaw) turned by ``yaw`` about z, as plain floats.

    ``(c·dx − s·dy, s·dx + c·dy, dz, dyaw + yaw)``: the (x, y) part rotated, dz kept, the heading not wrapped.
    This is ``(0, 0, 0, yaw) ⊕ step`` without adding the zeros (which would turn a −0.0 into 0.0).
    """
    dx, dy = step[0], step[1]
    c, s = math.cos(yaw), math.sin(yaw)
    return (c * dx - s * dy, s * dx + c * dy, step[2], step[3] + yaw)


# ------------------------------------------------------------------------------ yaw ↔ quaternion


def quaternion_from_yaw(yaw: float) -> tuple[float, float, float, float]:
    """Return the unit quaternion ``(qx, qy, qz, qw)`` = ``(0, 0, sin(yaw/2), cos(yaw/2))`` of a rotation about z.

    ``yaw`` is in radians, counter-clockwise about +z; for yaw in (−π, π] ``qw ≥ 0``.
    """
    half = 0.5 * float(yaw)
    return 0.0, 0.0, math.sin(half), math.cos(half)


def quaternions_from_yaws(yaw: npt.ArrayLike) -> FloatArray:
    """Return the quaternions (..., 4) ``(0, 0, sin(yaw/2), cos(yaw/2))`` of yaws (...) with numpy's sin and cos."""
    half = 0.5 * np.asarray(yaw, dtype=np.float64)
    out = np.zeros((*half.shape, 4), dtype=np.float64)
    out[..., 2] = np.sin(half)
    out[..., 3] = np.cos(half)
    return out


def yaw_of_unit_quaternion(qx: float, qy: float, qz: float, qw: float) -> float:
    """Return the yaw (ZYX Euler convention) ``atan2(2(qw·qz + qx·qy), 1 − 2(qy² + qz²))`` of a unit quaternion.

    The result is ``math.atan2``'s, in [−π, π]; the quaternion is taken as given (normalise it first).
    """
    return math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def yaw_from_quaternion(qx: float, qy: float, qz: float, qw: float) -> float:
    """Return the yaw (rotation about z, ZYX Euler convention) of a quaternion, in (−π, π].

    The quaternion is normalised first (each component divided by its norm), so any non-zero scaling of a unit
    quaternion gives the same yaw; then :func:`yaw_of_unit_quaternion`, −π given as π.

    Raises:
        ValueError: the quaternion's norm is zero or not finite.
    """
    norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if norm == 0.0 or not math.isfinite(norm):
        msg = f"quaternion has no orientation: {(qx, qy, qz, qw)!r}"
        raise ValueError(msg)
    yaw = yaw_of_unit_quaternion(qx / norm, qy / norm, qz / norm, qw / norm)
    return math.pi if yaw == -math.pi else yaw

"""4-DoF rigid transforms of experience poses (x, y, z, yaw): the SE(3) subgroup of rotations about z.

Experience poses are stored as rows ``(x, y, z, yaw)`` (docs/architecture.md, ``em_pose``).
A pose is also a transform: ``T_map_body`` maps body coordinates to the map frame.
Every function broadcasts over leading axes, so whole experience maps are
transformed at once (no per-experience Python loop).

Menezes et al. (2023) Eqs. 13–14 transform the partial map's poses by a 2-D
rotation about the matched experience plus a translation; written as poses this
is ``p' = T ⊕ p`` with ``T = T_loaded ⊕ T_partial⁻¹`` (the generalisation to
x, y, z, yaw used here).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt


def wrap_angle(angle: npt.ArrayLike) -> np.ndarray:
    """Return angles wrapped to (−π, π]."""
    a = np.asarray(angle, dtype=np.float64)
    wrapped = np.mod(a + math.pi, 2.0 * math.pi) - math.pi
    return np.where(wrapped == -math.pi, math.pi, wrapped)


def _as_poses(poses: npt.ArrayLike) -> np.ndarray:
    p = np.asarray(poses, dtype=np.float64)
    if p.shape[-1:] != (4,):
        msg = f"poses must have shape (..., 4) as (x, y, z, yaw), got {p.shape}"
        raise ValueError(msg)
    return p


def compose(a: npt.ArrayLike, b: npt.ArrayLike, turn: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
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


def inverse(a: npt.ArrayLike) -> np.ndarray:
    """Return ``a⁻¹`` (..., 4): ``a ⊕ a⁻¹ = a⁻¹ ⊕ a = identity``."""
    pa = _as_poses(a)
    c, s = np.cos(pa[..., 3]), np.sin(pa[..., 3])
    out = np.empty_like(pa)
    out[..., 0] = -(c * pa[..., 0] + s * pa[..., 1])
    out[..., 1] = -(-s * pa[..., 0] + c * pa[..., 1])
    out[..., 2] = -pa[..., 2]
    out[..., 3] = wrap_angle(-pa[..., 3])
    return out


def relative(a: npt.ArrayLike, b: npt.ArrayLike) -> np.ndarray:
    """Return ``a⁻¹ ⊕ b``: pose ``b`` in the frame of ``a`` (an experience link's transform, ``from`` = a)."""
    return compose(inverse(a), b)


def alignment(loaded: npt.ArrayLike, partial: npt.ArrayLike) -> np.ndarray:
    """Return ``T = T_loaded ⊕ T_partial⁻¹``, the transform taking the partial pose onto the loaded one.

    Generalises Menezes et al. Eqs. 13–14 (Δθ = θ_l − θ_p, rotation about the matched
    experience, then translation onto it) to x, y, z, yaw.
    """
    return compose(loaded, inverse(partial))


def to_matrix(pose: npt.ArrayLike) -> np.ndarray:
    """Return the homogeneous 4×4 matrix (..., 4, 4) of poses (..., 4)."""
    p = _as_poses(pose)
    c, s = np.cos(p[..., 3]), np.sin(p[..., 3])
    m = np.zeros((*p.shape[:-1], 4, 4), dtype=np.float64)
    m[..., 0, 0], m[..., 0, 1], m[..., 1, 0], m[..., 1, 1] = c, -s, s, c
    m[..., 2, 2] = 1.0
    m[..., 3, 3] = 1.0
    m[..., :3, 3] = p[..., :3]
    return m


def from_matrix(matrix: npt.ArrayLike, atol: float = 1e-9) -> np.ndarray:
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

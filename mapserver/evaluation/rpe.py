"""Relative pose error (RPE): the drift of a trajectory over segments of a given length of the ground truth.

Sturm et al. 2012 (TUM RGB-D benchmark), Eq. 1, as evo's ``evo_rpe`` computes it with ``--delta D
--delta_unit m --pairs_from_reference``: the reference path is walked from its first pose, and a pair
``(i, j)`` is closed at the first pose ``j`` where the distance travelled since ``i`` reaches ``D`` (the
next pair starts at ``j``: consecutive pairs). Each pair's error is

    E_ij = (Q_i⁻¹ Q_j)⁻¹ (P_i⁻¹ P_j)

for reference poses ``Q`` and estimated poses ``P`` (SE(3)); the translation error is ``‖t(E_ij)‖`` and the
rotation error the angle of ``R(E_ij)``. RPE needs no alignment: a rigid motion of either trajectory
leaves every ``Q_i⁻¹ Q_j`` and ``P_i⁻¹ P_j`` unchanged. tests/mapserver/test_evo.py checks the figures
against ``evo_rpe`` on the same trajectories.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation, Slerp

FloatArray = npt.NDArray[np.float64]

DELTAS_M = (1.0, 10.0)
"""The segment lengths ``evaluate`` and ``report`` give the RPE for (odometry papers' 1 m and 10 m)."""


@dataclass(frozen=True, slots=True)
class RPEResult:
    """RPE over one segment length: how many pairs, and the translation (m) and rotation (deg) errors."""

    delta_m: float
    pairs: int
    trans_rmse: float | None
    trans_mean: float | None
    trans_max: float | None
    rot_rmse_deg: float | None

    def as_dict(self) -> dict[str, float | int | None]:
        """Return the figures as plain Python values (the ``rpe`` entries of ``evaluate --json``)."""
        return {
            "delta_m": self.delta_m, "pairs": self.pairs, "trans_rmse": self.trans_rmse, "trans_mean": self.trans_mean,
            "trans_max": self.trans_max, "rot_rmse_deg": self.rot_rmse_deg,
        }  # fmt: skip


def pairs_by_path(positions: FloatArray, delta_m: float) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """Return the consecutive pairs ``(i, j)`` of poses ``delta_m`` of path apart (``evo``'s ``filter_pairs_by_path``).

    The distance travelled is summed step by step from the pair's first pose, as evo sums it, so that a
    step that lands exactly on ``delta_m`` closes the pair in both.
    """
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1).tolist()
    ends = [0]
    travelled = 0.0
    for k, step in enumerate(steps, start=1):  # sequential by definition: the sum restarts at each pair's end
        travelled += step
        if travelled >= delta_m:
            ends.append(k)
            travelled = 0.0
    ids = np.asarray(ends, dtype=np.int64)
    return ids[:-1], ids[1:]


def relative_pose_error(
    ref_xyz: FloatArray, ref_rot: Rotation, est_xyz: FloatArray, est_rot: Rotation, delta_m: float
) -> RPEResult:
    """Return the RPE of an estimate against its reference at the same instants (both (N, 3) and N rotations)."""
    first, last = pairs_by_path(ref_xyz, delta_m)
    if first.size == 0:
        return RPEResult(delta_m, 0, None, None, None, None)
    ref_rot_rel, ref_t_rel = _relative(ref_xyz, ref_rot, first, last)
    est_rot_rel, est_t_rel = _relative(est_xyz, est_rot, first, last)
    # E = Q_rel⁻¹ P_rel: rotation R_Q⁻¹ R_P, translation R_Q⁻¹ (t_P − t_Q)
    error_rot = ref_rot_rel.inv() * est_rot_rel
    error_t = ref_rot_rel.inv().apply(est_t_rel - ref_t_rel)
    trans = np.linalg.norm(error_t, axis=1)
    angle = np.degrees(error_rot.magnitude())
    return RPEResult(
        delta_m=delta_m, pairs=int(first.size), trans_rmse=float(np.sqrt(np.mean(trans * trans))),
        trans_mean=float(trans.mean()), trans_max=float(trans.max()),
        rot_rmse_deg=float(np.sqrt(np.mean(angle * angle))),
    )  # fmt: skip


def _relative(
    xyz: FloatArray, rot: Rotation, first: npt.NDArray[np.int64], last: npt.NDArray[np.int64]
) -> tuple[Rotation, FloatArray]:
    """Return ``T_i⁻¹ T_j`` for every pair: rotation ``R_i⁻¹ R_j`` and translation ``R_i⁻¹ (t_j − t_i)``."""
    inverse = rot[first].inv()
    return inverse * rot[last], inverse.apply(xyz[last] - xyz[first])


def reference_at(
    stamps: FloatArray, positions: FloatArray, quat_xyzw: FloatArray, query: FloatArray
) -> tuple[FloatArray, Rotation]:
    """Return a reference trajectory at ``query`` stamps (inside its span): positions linearly, rotations by slerp."""
    order = np.argsort(stamps, kind="stable")
    stamps, positions, quat_xyzw = stamps[order], positions[order], quat_xyzw[order]
    keep = np.concatenate([[True], np.diff(stamps) > 0])  # Slerp needs increasing times
    stamps, positions, quat_xyzw = stamps[keep], positions[keep], quat_xyzw[keep]
    xyz = np.column_stack([np.interp(query, stamps, positions[:, axis]) for axis in range(3)])
    if stamps.size == 1:
        return xyz, Rotation.from_quat(np.repeat(quat_xyzw, query.size, axis=0))
    return xyz, Slerp(stamps, Rotation.from_quat(quat_xyzw))(np.clip(query, stamps[0], stamps[-1]))


def yaw_rotations(yaw: npt.ArrayLike) -> Rotation:
    """Return rotations about z by ``yaw`` (rad): a 4-DoF map's experience orientations."""
    return Rotation.from_euler("z", np.asarray(yaw, dtype=np.float64).reshape(-1, 1))

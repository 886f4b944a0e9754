"""A map JSON document against ground truth: the experiences' and the odometry's APE, RPE and Hausdorff distance.

Planar maps (every experience has ``z == 0``: 3-DoF RatSLAM) are evaluated in the xy plane: alignment is a
rotation about z plus a translation in xy, and the ground truth's z is ignored. Maps with height are
evaluated in 3-D with a full SE(3) alignment. :class:`MapEvaluation` is what :func:`evaluate_map` reports and
:mod:`mapserver.evaluation.plots` draws.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from mapserver.errors import InputError
from mapserver.evaluation.ape import APEResult, ape_positions, hausdorff, interpolate_poses
from mapserver.evaluation.rpe import DELTAS_M, RPEResult, reference_at, relative_pose_error, yaw_rotations
from mapserver.formats import Trajectory, odometry_trajectory

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class MapEvaluation:
    """Everything :func:`evaluate_map` and the plot need (positions in 3-D; z = 0 when planar)."""

    dims: int
    session: str | None
    exp_ids: list[int]
    exp_stamps: FloatArray
    exp_xyz: FloatArray  # the experiences' map positions, before alignment
    exp_yaw: FloatArray  # and headings (rad)
    exp_aligned: FloatArray
    links: list[tuple[int, int, str]]
    gt: Trajectory
    gt_xyz: FloatArray
    ape: APEResult
    R3: FloatArray
    t3: FloatArray
    hausdorff: float
    odo_stamps: FloatArray | None
    odo_aligned: FloatArray | None
    odo_ape: APEResult | None
    z_rmse: float | None
    odo_z_rmse: float | None


def _lift(R: FloatArray, t: FloatArray) -> tuple[FloatArray, FloatArray]:
    if R.shape == (3, 3):
        return R, t
    R3 = np.eye(3)
    R3[:2, :2] = R
    return R3, np.array([t[0], t[1], 0.0])


def align_map(
    doc: Mapping[str, Any],
    ground_truth: Trajectory,
    *,
    odometry: Trajectory | None,
    max_diff_s: float,
    session: str | None,
) -> MapEvaluation:
    """Align the experiences (of ``session``) and the odometry to the ground truth and measure both."""
    exps = _experiences_to_evaluate(doc, ground_truth, session)
    exp_ids = [int(e["id"]) for e in exps]
    stamps = np.array([float(e["stamp"]) for e in exps])
    xyz = np.array([[float(e["x"]), float(e["y"]), float(e["z"])] for e in exps])
    dims = 3 if np.any(xyz[:, 2] != 0.0) else 2
    gt = ground_truth.sorted()
    gt_xyz = gt.positions_xyz.copy()
    if dims == 2:
        gt_xyz[:, 2] = 0.0
    gt_plane = Trajectory(gt.stamps_s, gt_xyz, gt.quat_xyzw)
    ape, R3, t3, aligned, z_rmse = _align_experiences(gt_plane, stamps, xyz, dims, max_diff_s)
    covered = covered_by(gt.stamps_s, stamps) if session is not None else np.ones(len(gt), dtype=bool)
    dist = hausdorff(aligned[:, :dims], gt_xyz[covered][:, :dims])
    links = _link_indices(doc, exp_ids)
    if odometry is None and (session is None or len(doc.get("sessions", [])) <= 1):
        odometry = odometry_trajectory(doc)
    odo_stamps, odo_aligned, odo_ape, odo_z_rmse = _align_odometry(odometry, gt_plane, dims, max_diff_s)
    return MapEvaluation(
        dims=dims,
        session=session,
        exp_ids=exp_ids,
        exp_stamps=stamps,
        exp_xyz=xyz,
        exp_yaw=np.array([float(e.get("yaw", 0.0)) for e in exps]),
        exp_aligned=aligned,
        links=links,
        gt=gt,
        gt_xyz=gt_xyz,
        ape=ape,
        R3=R3,
        t3=t3,
        hausdorff=dist,
        odo_stamps=odo_stamps,
        odo_aligned=odo_aligned,
        odo_ape=odo_ape,
        z_rmse=z_rmse,
        odo_z_rmse=odo_z_rmse,
    )


def covered_by(gt_stamps: FloatArray, stamps: FloatArray) -> npt.NDArray[np.bool_]:
    """Return which ground-truth samples a session's own experiences cover in time.

    A sample is covered when one of the experience ``stamps`` lies within twice their median spacing of it
    (at least 1 s): the stretches where the session made its own experiences. Where it drove through places
    another session had mapped, it made none, and those stretches are left to that session's figures.
    """
    ordered = np.sort(stamps)
    spacing = float(np.median(np.diff(ordered))) if ordered.size > 1 else 0.0
    reach = max(2.0 * spacing, 1.0)
    after = np.clip(np.searchsorted(ordered, gt_stamps), 0, ordered.size - 1)  # first stamp at or after
    before = np.maximum(after - 1, 0)
    nearest = np.minimum(np.abs(gt_stamps - ordered[before]), np.abs(gt_stamps - ordered[after]))
    covered = nearest <= reach
    return covered if covered.any() else np.ones(gt_stamps.size, dtype=bool)


def _experiences_to_evaluate(
    doc: Mapping[str, Any], ground_truth: Trajectory, session: str | None
) -> list[Mapping[str, Any]]:
    """Return the map's experiences (of ``session``) in stamp order; refuse an empty selection or ground truth."""
    exps = list(doc["experiences"])
    if session is not None:
        names = sorted({str(e["session"]) for e in exps})
        exps = [e for e in exps if e["session"] == session]
        if not exps:
            msg = f"map has no experience of session {session!r} (sessions: {', '.join(names) or 'none'})"
            raise InputError(msg)
    if not exps:
        msg = "map has no experiences to evaluate"
        raise InputError(msg)
    if len(ground_truth) == 0:
        msg = "ground truth holds no pose"
        raise InputError(msg)
    exps.sort(key=lambda e: float(e["stamp"]))
    return exps


def _align_experiences(
    gt_plane: Trajectory, stamps: FloatArray, xyz: FloatArray, dims: int, max_diff_s: float
) -> tuple[APEResult, FloatArray, FloatArray, FloatArray, float | None]:
    """Return the experiences' APE at their stamps, its (R, t) in 3-D, the aligned positions and the z RMSE."""
    gt_at = interpolate_poses(gt_plane, stamps, max_diff_s=max_diff_s)
    mask = ~np.isnan(gt_at[:, 0])
    if not mask.any():
        msg = (
            f"no experience stamp falls within the ground truth's time span "
            f"[{gt_plane.stamps_s[0]:.3f}, {gt_plane.stamps_s[-1]:.3f}] s (experiences span "
            f"[{stamps[0]:.3f}, {stamps[-1]:.3f}] s)"
        )
        raise InputError(msg)
    ape = ape_positions(gt_at[mask][:, :dims], xyz[mask][:, :dims])
    R3, t3 = _lift(ape.R, ape.t)
    aligned = xyz @ R3.T + t3
    z_rmse = _z_rmse(gt_at[mask], aligned[mask]) if dims == 3 else None
    return ape, R3, t3, aligned, z_rmse


def _link_indices(doc: Mapping[str, Any], exp_ids: list[int]) -> list[tuple[int, int, str]]:
    """Return the links between the evaluated experiences as (from, to, kind), endpoints indexing ``exp_ids``."""
    index = {eid: i for i, eid in enumerate(exp_ids)}
    return [
        (index[int(link["from"])], index[int(link["to"])], str(link["kind"]))
        for link in doc["links"]
        if int(link["from"]) in index and int(link["to"]) in index
    ]


def _align_odometry(
    odometry: Trajectory | None, gt_plane: Trajectory, dims: int, max_diff_s: float
) -> tuple[FloatArray | None, FloatArray | None, APEResult | None, float | None]:
    """Return the odometry aligned to the ground truth on its own: stamps, aligned positions, APE, z RMSE."""
    if odometry is None or len(odometry) == 0:
        return None, None, None, None
    odo = odometry.sorted()
    odo_xyz = odo.positions_xyz.copy()
    if dims == 2:
        odo_xyz[:, 2] = 0.0
    gt_at_odo = interpolate_poses(gt_plane, odo.stamps_s, max_diff_s=max_diff_s)
    omask = ~np.isnan(gt_at_odo[:, 0])
    if not omask.any():
        return None, None, None, None
    odo_ape = ape_positions(gt_at_odo[omask][:, :dims], odo_xyz[omask][:, :dims])
    oR, ot = _lift(odo_ape.R, odo_ape.t)
    odo_aligned = odo_xyz @ oR.T + ot
    odo_z_rmse = _z_rmse(gt_at_odo[omask], odo_aligned[omask]) if dims == 3 else None
    return odo.stamps_s, odo_aligned, odo_ape, odo_z_rmse


def _z_rmse(ref: FloatArray, aligned: FloatArray) -> float:
    """RMSE of the height component of already aligned position pairs."""
    dz = ref[:, 2] - aligned[:, 2]
    return float(np.sqrt(np.mean(dz * dz)))


def evaluate_map(
    doc: Mapping[str, Any],
    ground_truth: Trajectory,
    *,
    odometry: Trajectory | None = None,
    max_diff_s: float = 0.05,
    session: str | None = None,
) -> dict[str, Any]:
    """Accuracy of a map JSON document against a ground-truth trajectory.

    Ground truth is linearly interpolated at every experience stamp inside its time span (stamps up to
    ``max_diff_s`` outside it take the end pose; others are left out of the APE). The experiences are
    aligned rigidly to those positions (Umeyama 1991) and the APE RMSE is taken. The Hausdorff distance
    (OpenRatSLAM2 Eq. 9) is between *all* aligned experience positions and all ground-truth positions; for
    one ``session`` of the map, the ground truth it covers with experiences of its own (:func:`covered_by`).
    Planar maps (every ``z == 0``) are evaluated in xy.

    The odometry baseline comes from ``odometry`` when given, else from the map's ``"odometry"`` extension
    key (``[[stamp, x, y, z], ...]``; used only when no ``session`` is selected or the map has one session),
    and is aligned to the ground truth on its own.

    Args:
        doc: map JSON document.
        ground_truth: reference trajectory in any frame (only its positions are used).
        odometry: raw dead-reckoning trajectory of the same log, optional.
        max_diff_s: tolerance for stamps just outside the ground truth's span, seconds.
        session: evaluate only the experiences of this session (the ground truth is of one log).

    Returns:
        ``{"ape_rmse", "odometry_ape_rmse" (None without odometry), "hausdorff", "experiences" (count),
        "aligned" (experiences with ground truth), "ape_mean", "ape_max", "odometry_aligned", "dims",
        "session", "ape_z_rmse", "odometry_ape_z_rmse" (height part of the aligned errors; None for planar
        maps), "alignment": {"rotation", "translation"}, "rpe" (:func:`map_rpe` of the experiences: one entry
        per segment length, 1 m and 10 m), "odometry_rpe" (the same for ``odometry`` when given, which has
        orientations; None otherwise)}``, plain Python values.

    Raises:
        InputError: the map has no experience (of ``session``), or no experience stamp meets the ground truth.

    """
    ev = align_map(doc, ground_truth, odometry=odometry, max_diff_s=max_diff_s, session=session)
    odometry_rpe = None
    if odometry is not None and len(odometry):  # a file's odometry has orientations; the map's own has none
        odo = odometry.sorted()
        odometry_rpe = map_rpe(ground_truth, odo.stamps_s, odo.positions_xyz, odo_yaw(odo), ev.dims)
    return {
        "ape_rmse": ev.ape.rmse,
        "odometry_ape_rmse": ev.odo_ape.rmse if ev.odo_ape is not None else None,
        "hausdorff": ev.hausdorff,
        "experiences": len(ev.exp_ids),
        "aligned": ev.ape.n,
        "ape_mean": ev.ape.mean,
        "ape_max": ev.ape.max,
        "odometry_aligned": ev.odo_ape.n if ev.odo_ape is not None else 0,
        "dims": ev.dims,
        "session": ev.session,
        "ape_z_rmse": ev.z_rmse,
        "odometry_ape_z_rmse": ev.odo_z_rmse,
        "alignment": {"rotation": ev.R3.tolist(), "translation": ev.t3.tolist()},
        "rpe": map_rpe(ground_truth, ev.exp_stamps, ev.exp_xyz, ev.exp_yaw, ev.dims),
        "odometry_rpe": odometry_rpe,
    }


def map_rpe(
    ground_truth: Trajectory, stamps: FloatArray, xyz: FloatArray, yaw: FloatArray, dims: int
) -> list[dict[str, float | int | None]]:
    """Return the RPE (:mod:`mapserver.evaluation.rpe`) of poses ``xyz``, ``yaw`` at ``stamps``, over 1 m and 10 m.

    Only the stamps inside the ground truth's span count. The reference's orientation is reduced to its
    yaw (a 4-DoF map holds no roll or pitch), and planar maps (``dims`` 2) are compared in xy.
    """
    gt = ground_truth.sorted()
    inside = (stamps >= gt.stamps_s[0]) & (stamps <= gt.stamps_s[-1])
    if inside.sum() < 2:
        return [RPEResult(delta, 0, None, None, None, None).as_dict() for delta in DELTAS_M]
    ref_xyz, ref_rot = reference_at(gt.stamps_s, gt.positions_xyz, gt.quat_xyzw, stamps[inside])
    ref_yaw = yaw_rotations(ref_rot.as_euler("ZYX")[:, 0])
    est_xyz = xyz[inside].copy()
    if dims == 2:
        ref_xyz[:, 2] = 0.0
        est_xyz[:, 2] = 0.0
    est_rot = yaw_rotations(yaw[inside])
    return [relative_pose_error(ref_xyz, ref_yaw, est_xyz, est_rot, delta).as_dict() for delta in DELTAS_M]


def odo_yaw(trajectory: Trajectory) -> FloatArray:
    """Return the yaw (rad) of each pose of a trajectory (ZYX Euler angles of its quaternions)."""
    return np.asarray(Rotation.from_quat(trajectory.quat_xyzw).as_euler("ZYX")[:, 0], dtype=np.float64)

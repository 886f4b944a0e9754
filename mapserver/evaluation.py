"""Accuracy of a map against ground truth: association, Umeyama alignment, APE, Hausdorff, plots.

Everything here is a re-implementation on numpy/scipy (no evo, which is GPL):

* **APE** (absolute pose error, translation part): associate estimate and reference poses by time, align
  the estimate rigidly to the reference by least squares (Umeyama 1991), then take the RMSE of the remaining
  position differences.
* **Place recognition** (:func:`place_recognition`): from the map's per-frame template record, the share
  of revisiting frames that recognised the place from an earlier visit, and the share of false matches.
* **Hausdorff distance** (OpenRatSLAM2 Eq. 9): ``d_H(A, B) = max(sup_a inf_b d(a, b), sup_b inf_a d(a, b))``
  between the aligned experience positions and the ground-truth positions. It needs no association, so it
  suits maps whose node count the algorithm chooses, but it ignores timing.

Planar maps (every experience has ``z == 0``: 3-DoF RatSLAM) are evaluated in the xy plane: alignment is a
rotation about z plus a translation in xy, and the ground truth's z is ignored. Maps with height are
evaluated in 3-D with a full SE(3) alignment.

References:
    S. Umeyama, "Least-squares estimation of transformation parameters between two point patterns",
    IEEE TPAMI 13(4), 1991, pp. 376-380.

"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from mapserver.errors import InputError
from mapserver.formats import PathLike, Trajectory, atomic_write_bytes, odometry_trajectory
from mapserver.rpe import DELTAS_M, RPEResult, reference_at, relative_pose_error, yaw_rotations

if TYPE_CHECKING:
    from matplotlib.axes import Axes

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_RANK_TOL = 1e-10
"""Singular values below ``_RANK_TOL`` × the largest one count as zero when testing for degeneracy."""


@dataclass(frozen=True)
class APEResult:
    """Translation APE statistics after alignment.

    Attributes:
        rmse: root mean square of the position errors (m).
        mean: mean position error (m).
        max: largest position error (m).
        n: number of pose pairs.
        R: (k, k) rotation applied to the estimate (identity without alignment).
        t: (k,) translation applied to the estimate (zero without alignment).

    """

    rmse: float
    mean: float
    max: float
    n: int
    R: FloatArray
    t: FloatArray


# ----------------------------------------------------------------------------------------------- association


def associate(ref: Trajectory, est: Trajectory, max_diff_s: float = 0.05) -> tuple[IntArray, IntArray]:
    """Associate poses of two trajectories by nearest stamp, one-to-one.

    Each estimate pose takes the reference pose nearest in time (``np.searchsorted`` on the sorted reference
    stamps; on a tie the earlier one). Pairs further apart than ``max_diff_s`` are dropped. When several
    estimate poses take the same reference pose, only the closest in time keeps it (ties: the earlier
    estimate pose), so the association is one-to-one. This is greedy: a dropped estimate pose does not fall
    back to its second-nearest reference pose.

    Args:
        ref: reference trajectory (any stamp order).
        est: estimated trajectory (any stamp order).
        max_diff_s: largest accepted stamp difference, seconds.

    Returns:
        ``(idx_ref, idx_est)``: int64 index arrays of equal length into ``ref`` and ``est`` (their original
        order), sorted by the estimate's stamp.

    """
    empty = np.zeros(0, dtype=np.int64)
    if len(ref) == 0 or len(est) == 0:
        return empty, empty.copy()
    r_order = np.argsort(ref.stamps_s, kind="stable")
    e_order = np.argsort(est.stamps_s, kind="stable")
    rs = ref.stamps_s[r_order]
    es = est.stamps_s[e_order]
    pos = np.searchsorted(rs, es, side="left")
    left = np.clip(pos - 1, 0, rs.shape[0] - 1)
    right = np.clip(pos, 0, rs.shape[0] - 1)
    d_left = np.abs(es - rs[left])
    d_right = np.abs(rs[right] - es)
    cand = np.where(d_right < d_left, right, left)
    diff = np.abs(rs[cand] - es)
    ok = np.flatnonzero(diff <= max_diff_s)
    r_idx = cand[ok]
    d = diff[ok]
    # One-to-one: per reference index keep the closest estimate (lexsort: last key is the primary key).
    order = np.lexsort((ok, d, r_idx))
    r_sorted = r_idx[order]
    first = np.ones(order.shape[0], dtype=bool)
    first[1:] = r_sorted[1:] != r_sorted[:-1]
    keep = np.sort(order[first])
    return r_order[r_idx[keep]].astype(np.int64), e_order[ok[keep]].astype(np.int64)


def interpolate_poses(traj: Trajectory, stamps: npt.ArrayLike, *, max_diff_s: float = 0.0) -> FloatArray:
    """Positions of a trajectory at given stamps by linear interpolation.

    Used to read ground truth at experience or frame stamps that fall between ground-truth samples. Stamps
    outside the trajectory's time span take the first/last position when they are within ``max_diff_s`` of
    it, and NaN otherwise. Gaps in the trajectory are interpolated across whatever their length.

    Args:
        traj: the trajectory (any stamp order; it is sorted first).
        stamps: (M,) query stamps, seconds.
        max_diff_s: how far outside the span a stamp may be and still take the end position.

    Returns:
        (M, 3) positions; rows of stamps that cannot be served are NaN.

    """
    query = np.asarray(stamps, dtype=np.float64).reshape(-1)
    out = np.full((query.shape[0], 3), np.nan)
    if len(traj) == 0 or query.shape[0] == 0:
        return out
    t = traj.sorted()
    ts = t.stamps_s
    inside = (query >= ts[0] - max_diff_s) & (query <= ts[-1] + max_diff_s)
    for axis in range(3):
        out[inside, axis] = np.interp(query[inside], ts, t.positions_xyz[:, axis])
    return out


# ----------------------------------------------------------------------------------------------- alignment


def _rotation_z(theta: float) -> FloatArray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def umeyama_alignment(
    src: npt.ArrayLike, dst: npt.ArrayLike, with_scale: bool = False
) -> tuple[FloatArray, FloatArray, float]:
    """Least-squares similarity (or rigid) transform mapping ``src`` onto ``dst`` (Umeyama 1991).

    Minimises ``Σ_i ‖dst_i − (s·R·src_i + t)‖²`` over rotations ``R`` (det +1), translations ``t`` and, with
    ``with_scale``, a scale ``s > 0``. With centred point sets and ``Σ = (1/N) Σ_i d_i s_iᵀ = U D Vᵀ``
    (SVD), ``R = U S Vᵀ`` where ``S = diag(1, …, 1, −1)`` when ``det(U)·det(V) < 0`` (the best orthogonal
    matrix would be a reflection; Umeyama's Lemma) and the identity otherwise;
    ``s = tr(D S) / σ²_src`` and ``t = μ_dst − s·R·μ_src``.

    The solution is unique when ``rank(Σ) ≥ k − 1`` (k the dimension). Degenerate inputs are handled so that
    the result stays meaningful for ground vehicles:

    * k = 3 and ``rank(Σ) < 2`` (N < 3, or all points collinear or coincident): the rotation is restricted to
      one about z, found by the same method on the xy coordinates (identity when those are degenerate too:
      all xy equal);
    * k = 2 and ``rank(Σ) = 0`` (all points coincident): ``R`` is the identity;
    * one point: ``R = I``, ``t = dst − src``.

    Args:
        src: (N, k) points to move, k = 2 or 3.
        dst: (N, k) target points.
        with_scale: also estimate a scale ``s`` (otherwise ``s = 1``).

    Returns:
        ``(R, t, s)``: (k, k) rotation, (k,) translation and scale with ``dst ≈ s·R·src + t``.

    Raises:
        ValueError: shapes differ, k is not 2 or 3, or there are no points.

    """
    a = np.asarray(src, dtype=np.float64)
    b = np.asarray(dst, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] not in (2, 3):
        msg = f"src and dst must both be (N, 2) or (N, 3), got {a.shape!r} and {b.shape!r}"
        raise ValueError(msg)
    n, k = a.shape
    if n == 0:
        msg = "umeyama_alignment needs at least one point pair"
        raise ValueError(msg)
    mu_a = a.mean(axis=0)
    mu_b = b.mean(axis=0)
    xa = a - mu_a
    xb = b - mu_b
    var_a = float((xa * xa).sum()) / n
    cov = xb.T @ xa / n
    U, D, Vt = np.linalg.svd(cov)
    rank = int(np.count_nonzero(_RANK_TOL * D[0] < D)) if D[0] > 0.0 else 0
    if rank >= k - 1:
        S = np.ones(k)
        if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
            S[-1] = -1.0
        R = (U * S) @ Vt
        scale = float((D * S).sum()) / var_a if with_scale and var_a > 0.0 else 1.0
    else:
        if k == 3:
            R2, _, _ = umeyama_alignment(a[:, :2], b[:, :2])
            R = np.eye(3)
            R[:2, :2] = R2
        else:
            R = np.eye(2)
        scale = float((xb * (xa @ R.T)).sum()) / (var_a * n) if with_scale and var_a > 0.0 else 1.0
    t = mu_b - scale * (R @ mu_a)
    return R, t, scale


# ----------------------------------------------------------------------------------------------- metrics


def ape_positions(ref_xyz: npt.ArrayLike, est_xyz: npt.ArrayLike, *, align: bool = True) -> APEResult:
    """Compute the translation APE of already associated position pairs.

    Args:
        ref_xyz: (N, k) reference positions.
        est_xyz: (N, k) estimated positions, row i paired with ``ref_xyz[i]``.
        align: align the estimate to the reference rigidly (Umeyama 1991, no scale) first.

    Returns:
        The statistics of ``‖ref_i − (R·est_i + t)‖``.

    Raises:
        ValueError: shapes differ or there are no pairs.

    """
    ref = np.asarray(ref_xyz, dtype=np.float64)
    est = np.asarray(est_xyz, dtype=np.float64)
    if ref.shape != est.shape or ref.ndim != 2:
        msg = f"ref and est must have the same (N, k) shape, got {ref.shape!r} and {est.shape!r}"
        raise ValueError(msg)
    if ref.shape[0] == 0:
        msg = "no pose pairs to compute the APE from"
        raise ValueError(msg)
    k = ref.shape[1]
    if align:
        R, t, _ = umeyama_alignment(est, ref)
    else:
        R, t = np.eye(k), np.zeros(k)
    err = np.linalg.norm(ref - (est @ R.T + t), axis=1)
    return APEResult(
        rmse=float(np.sqrt(np.mean(err * err))),
        mean=float(err.mean()),
        max=float(err.max()),
        n=int(err.shape[0]),
        R=R,
        t=t,
    )


def ape_rmse(ref: Trajectory, est: Trajectory, *, align: bool = True, max_diff_s: float = 0.05) -> APEResult:
    """Compute the translation APE of an estimated trajectory against a reference.

    Poses are associated by stamp (:func:`associate`), the estimate is aligned rigidly to the reference by
    least squares (Umeyama 1991) and the position errors are summarised.

    Args:
        ref: reference (ground-truth) trajectory.
        est: estimated trajectory.
        align: align rigidly before measuring (otherwise compare in the given frames).
        max_diff_s: largest stamp difference for an association, seconds.

    Returns:
        RMSE, mean, max, the number of pairs and the alignment ``(R, t)`` (3-D).

    Raises:
        InputError: no pose of ``est`` is within ``max_diff_s`` of a pose of ``ref``.

    """
    idx_ref, idx_est = associate(ref, est, max_diff_s)
    if idx_ref.shape[0] == 0:
        msg = f"no poses associated within {max_diff_s!r} s"
        raise InputError(msg)
    return ape_positions(ref.positions_xyz[idx_ref], est.positions_xyz[idx_est], align=align)


def hausdorff(a: npt.ArrayLike, b: npt.ArrayLike) -> float:
    """Symmetric Hausdorff distance between two point sets (OpenRatSLAM2 Eq. 9).

    ``d_H(A, B) = max(sup_{a∈A} inf_{b∈B} ‖a − b‖, sup_{b∈B} inf_{a∈A} ‖a − b‖)``, each point's nearest
    neighbour in the other set found exactly by a k-d tree: O((N + M) log(N + M)). (scipy's
    ``directed_hausdorff`` scans until a point closer than the running maximum turns up, which along two long
    trajectories is most of the other set: 51 s for two 100,000-point sets, 0.2 s here.)

    Args:
        a: (N, k) points.
        b: (M, k) points.

    Returns:
        The distance, in the points' unit.

    Raises:
        ValueError: a set is empty or the dimensions differ.

    """
    pa = np.asarray(a, dtype=np.float64)
    pb = np.asarray(b, dtype=np.float64)
    if pa.ndim != 2 or pb.ndim != 2 or pa.shape[1] != pb.shape[1]:
        msg = f"point sets must be (N, k) and (M, k), got {pa.shape!r} and {pb.shape!r}"
        raise ValueError(msg)
    if pa.shape[0] == 0 or pb.shape[0] == 0:
        msg = "hausdorff needs two non-empty point sets"
        raise ValueError(msg)
    a_to_b = np.asarray(cKDTree(pb).query(pa, k=1)[0], dtype=np.float64)
    b_to_a = np.asarray(cKDTree(pa).query(pb, k=1)[0], dtype=np.float64)
    return float(max(a_to_b.max(), b_to_a.max()))


# ----------------------------------------------------------------------------------------------- maps


@dataclass(frozen=True)
class _MapEvaluation:
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


def _evaluate(
    doc: Mapping[str, Any],
    ground_truth: Trajectory,
    *,
    odometry: Trajectory | None,
    max_diff_s: float,
    session: str | None,
) -> _MapEvaluation:
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
    return _MapEvaluation(
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
    ev = _evaluate(doc, ground_truth, odometry=odometry, max_diff_s=max_diff_s, session=session)
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
    """Return the RPE (:mod:`mapserver.rpe`) of poses ``xyz``, ``yaw`` at ``stamps`` over 1 m and 10 m of ground truth.

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


@dataclass(frozen=True)
class RecognitionSettings:
    """Radii and gap of the place-recognition rates (defaults suit metre-scale ground robots).

    Attributes:
        revisit_radius: R: a frame revisits a place when it is within R metres of an earlier frame.
        revisit_gap_s: T: that earlier frame must be more than T seconds earlier.
        match_radius: R′: a revisit frame is recognised when its template was created within R′ metres.
        false_radius: a matched frame is a false match when its template was created more than this far.

    """

    revisit_radius: float = 1.0
    revisit_gap_s: float = 20.0
    match_radius: float = 3.0
    false_radius: float = 5.0


@dataclass(frozen=True)
class _FrameTable:
    """The map's per-frame record with each frame's ground-truth position (NaN where it has none)."""

    stamps: FloatArray
    templates: IntArray
    created: npt.NDArray[np.bool_]
    positions: FloatArray
    known: npt.NDArray[np.bool_]

    @classmethod
    def of(cls, rows: npt.ArrayLike, ground_truth: Trajectory, max_diff_s: float) -> _FrameTable:
        """Return the table of ``[stamp, template, created]`` rows with positions read from ``ground_truth``."""
        table = np.asarray(rows, dtype=np.float64).reshape(-1, 3)
        stamps = table[:, 0]
        positions = interpolate_poses(ground_truth, stamps, max_diff_s=max_diff_s)
        return cls(stamps, table[:, 1].astype(np.int64), table[:, 2] != 0, positions, ~np.isnan(positions[:, 0]))


def _revisit_frames(frames: _FrameTable, idx: IntArray, s: RecognitionSettings) -> npt.NDArray[np.bool_]:
    """Return which frames revisit a place: within R of a frame (of ``idx``) more than T earlier."""
    revisit = np.zeros(frames.stamps.shape[0], dtype=bool)
    if idx.size:
        stamps, positions = frames.stamps, frames.positions
        tree = cKDTree(positions[idx])
        for k, neighbours in enumerate(tree.query_ball_point(positions[idx], r=s.revisit_radius)):
            i = idx[k]
            if neighbours and float(np.min(stamps[idx[neighbours]])) < stamps[i] - s.revisit_gap_s:
                revisit[i] = True
    return revisit


def _count_matches(
    frames: _FrameTable, idx: IntArray, revisit: npt.NDArray[np.bool_], s: RecognitionSettings
) -> tuple[int, int, int]:
    """Return (recognised revisits, matched frames, false matches) among the frames of ``idx``."""
    stamps, templates, created, positions = frames.stamps, frames.templates, frames.created, frames.positions
    # creating frame of every template (first created row)
    creator: dict[int, int] = {}
    for index in np.flatnonzero(created).tolist():
        creator.setdefault(int(templates[index]), index)
    recognised = 0
    matched = 0
    false = 0
    for i in idx.tolist():
        if created[i]:
            continue
        c = creator.get(int(templates[i]))
        if c is None or not frames.known[c]:
            continue
        matched += 1
        distance = float(np.linalg.norm(positions[c] - positions[i]))
        if distance > s.false_radius:
            false += 1
        if revisit[i] and stamps[c] < stamps[i] - s.revisit_gap_s and distance <= s.match_radius:
            recognised += 1
    return recognised, matched, false


def place_recognition(
    rows: npt.ArrayLike,
    ground_truth: Trajectory,
    settings: RecognitionSettings | None = None,
    *,
    max_diff_s: float = 0.05,
) -> dict[str, Any]:
    """Place-recognition rates of a processed log from its per-frame template record (map JSON ``frames``).

    Every frame gets its ground-truth position p (interpolated at its stamp t; frames outside the ground
    truth's span are left out), and every template the frame c that created it. With the settings' R, T,
    R′ and the false-match radius F:

    * **revisit frames**: frames i with an earlier frame j, ``t_j < t_i − T``, at ``‖p_j − p_i‖ ≤ R``;
    * **revisit_match_rate**: the fraction of revisit frames that matched (did not create) a template whose
      creating frame c is earlier than ``t_i − T`` and within ``‖p_c − p_i‖ ≤ R′``: the place was
      recognised from an earlier visit (for ``loop``: second-lap frames matched to first-lap templates);
    * **false_match_rate**: among all frames that matched an existing template, the fraction whose
      template was created more than F metres away.

    Args:
        rows: (N, 3) ``[stamp, template, created]`` per frame, in processing order.
        ground_truth: reference trajectory (3-D positions; planar ground truth has z = 0 or constant).
        settings: R, T, R′, F (defaults: 1 m, 20 s, 3 m, 5 m).
        max_diff_s: tolerance for stamps just outside the ground truth's span.

    Returns:
        ``{"revisit_frames", "revisit_matched", "revisit_match_rate" (None without revisits),
        "matched_frames", "false_matches", "false_match_rate" (None without matches), "frames_evaluated",
        "settings": {...}}``.

    """
    s = settings or RecognitionSettings()
    frames = _FrameTable.of(rows, ground_truth, max_diff_s)
    idx = np.flatnonzero(frames.known)
    revisit = _revisit_frames(frames, idx, s)
    recognised, matched, false = _count_matches(frames, idx, revisit, s)
    n_revisit = int(revisit.sum())
    return {
        "revisit_frames": n_revisit,
        "revisit_matched": recognised,
        "revisit_match_rate": recognised / n_revisit if n_revisit else None,
        "matched_frames": matched,
        "false_matches": false,
        "false_match_rate": false / matched if matched else None,
        "frames_evaluated": int(idx.size),
        "settings": {
            "revisit_radius": s.revisit_radius,
            "revisit_gap_s": s.revisit_gap_s,
            "match_radius": s.match_radius,
            "false_radius": s.false_radius,
        },
    }


def plot_map_vs_ground_truth(
    doc: Mapping[str, Any],
    gt: Trajectory,
    path: PathLike,
    *,
    odometry: Trajectory | None = None,
    title: str | None = None,
    max_diff_s: float = 0.05,
    session: str | None = None,
) -> None:
    """Plot a map, aligned to ground truth as in :func:`evaluate_map`, and write it as a PNG atomically.

    Top view with equal axes: the ground truth as a line, the aligned experiences as dots joined by their
    links (odometry links solid, loop/merge/manual links dashed), the aligned odometry dashed, and a legend
    with the APE RMSEs and the Hausdorff distance. Maps with height get a second panel, z against time.
    Uses matplotlib's Agg canvas directly (no pyplot, no global backend change).

    Args:
        doc: map JSON document.
        gt: ground-truth trajectory.
        path: destination PNG; its directory must exist.
        odometry: raw dead-reckoning trajectory, optional (else the map's ``"odometry"`` key).
        title: figure title (default: session names and experience count).
        max_diff_s: as for :func:`evaluate_map`.
        session: as for :func:`evaluate_map`.

    Raises:
        InputError: as for :func:`evaluate_map`.

    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    ev = _evaluate(doc, gt, odometry=odometry, max_diff_s=max_diff_s, session=session)
    three_d = ev.dims == 3
    fig = Figure(figsize=(13.0, 6.0) if three_d else (8.0, 7.0), dpi=110)
    FigureCanvasAgg(fig)
    if three_d:
        ax = fig.add_subplot(1, 2, 1)
        ax_z = fig.add_subplot(1, 2, 2)
    else:
        ax = fig.add_subplot(1, 1, 1)
        ax_z = None

    _plot_top_view(ax, ev)
    if ax_z is not None:
        _plot_height(ax_z, ev)

    if title is None:
        names = ev.session or ", ".join(str(s.get("name")) for s in doc.get("sessions", [])) or "map"
        title = f"{names}: {len(ev.exp_ids)} experiences vs ground truth"
    fig.suptitle(title)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    atomic_write_bytes(path, buf.getvalue())


def _plot_top_view(ax: Axes, ev: _MapEvaluation) -> None:
    """Draw the top view: ground truth, aligned odometry, experiences joined by their links, legend."""
    from matplotlib.collections import LineCollection

    ax.plot(ev.gt_xyz[:, 0], ev.gt_xyz[:, 1], "-", color="k", lw=1.2, label="ground truth")
    if ev.odo_aligned is not None and ev.odo_ape is not None:
        ax.plot(
            ev.odo_aligned[:, 0],
            ev.odo_aligned[:, 1],
            "--",
            color="C1",
            lw=1.0,
            label=f"odometry (APE RMSE {ev.odo_ape.rmse:.3f} m)",
        )
    xy = ev.exp_aligned[:, :2]
    odo_links = [(xy[i], xy[j]) for i, j, kind in ev.links if kind == "odometry"]
    other_links = [(xy[i], xy[j]) for i, j, kind in ev.links if kind != "odometry"]
    if odo_links:
        ax.add_collection(LineCollection(odo_links, colors="C0", linewidths=0.8, alpha=0.6))
    if other_links:
        ax.add_collection(
            LineCollection(other_links, colors="C3", linewidths=0.8, linestyles="dashed", alpha=0.7)
        )
    ax.scatter(
        xy[:, 0],
        xy[:, 1],
        s=9,
        color="C0",
        zorder=3,
        label=f"experiences (APE RMSE {ev.ape.rmse:.3f} m, Hausdorff {ev.hausdorff:.3f} m)",
    )
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)


def _plot_height(ax: Axes, ev: _MapEvaluation) -> None:
    """Draw the height panel: ground truth, aligned odometry and experiences, z against time."""
    ax.plot(ev.gt.stamps_s, ev.gt_xyz[:, 2], "-", color="k", lw=1.2, label="ground truth")
    if ev.odo_aligned is not None and ev.odo_stamps is not None:
        ax.plot(ev.odo_stamps, ev.odo_aligned[:, 2], "--", color="C1", lw=1.0, label="odometry")
    ax.scatter(ev.exp_stamps, ev.exp_aligned[:, 2], s=9, color="C0", zorder=3, label="experiences")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("z (m)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)

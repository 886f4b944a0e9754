"""Evaluation against ground truth: hand-computed numbers and independent methods, plus the CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.distance import cdist

from mapserver.cli import main
from mapserver.errors import InputError
from mapserver.evaluation import (
    RecognitionSettings,
    ape_positions,
    ape_rmse,
    associate,
    evaluate_map,
    hausdorff,
    interpolate_poses,
    place_recognition,
    plot_map_vs_ground_truth,
    umeyama_alignment,
)
from mapserver.formats import SessionInfo, Trajectory, map_json, write_map_json, write_tum

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _traj(stamps: Any, positions: Any) -> Trajectory:
    stamps = np.asarray(stamps, dtype=float)
    quats = np.zeros((stamps.shape[0], 4))
    quats[:, 3] = 1.0
    return Trajectory(stamps, np.asarray(positions, dtype=float), quats)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _rz(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------------------------- Umeyama


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_umeyama_recovers_known_transform(seed: int) -> None:
    rng = np.random.default_rng(seed)
    R = _random_rotation(rng)
    t = rng.normal(0.0, 10.0, 3)
    src = rng.normal(0.0, 5.0, (40, 3))
    dst = src @ R.T + t
    R_est, t_est, s = umeyama_alignment(src, dst)
    np.testing.assert_allclose(R_est, R, atol=1e-9)
    np.testing.assert_allclose(t_est, t, atol=1e-9)
    assert s == 1.0
    # with scale
    R_s, t_s, s_s = umeyama_alignment(src, 2.5 * dst, with_scale=True)
    assert s_s == pytest.approx(2.5, abs=1e-9)
    np.testing.assert_allclose(R_s, R, atol=1e-9)
    np.testing.assert_allclose(t_s, 2.5 * t, atol=1e-8)


def test_umeyama_never_returns_a_reflection() -> None:
    rng = np.random.default_rng(7)
    src = rng.normal(size=(30, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # mirror image: the best orthogonal map is a reflection
    R, _, _ = umeyama_alignment(src, dst)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_umeyama_planar_is_rotation_about_z() -> None:
    rng = np.random.default_rng(11)
    src = np.column_stack([rng.normal(size=(20, 2)), np.zeros(20)])
    R_true = _rz(0.7)
    dst = src @ R_true.T + np.array([3.0, -1.0, 0.0])
    R, t, _ = umeyama_alignment(src, dst)
    np.testing.assert_allclose(R, R_true, atol=1e-12)
    np.testing.assert_allclose(t, [3.0, -1.0, 0.0], atol=1e-12)


def test_umeyama_degenerate_inputs() -> None:
    # collinear in 3-D: rotation restricted to one about z
    src = np.column_stack([np.arange(5.0), np.zeros(5), np.zeros(5)])
    R_true = _rz(math.radians(30.0))
    dst = src @ R_true.T + np.array([1.0, 2.0, 3.0])
    R, t, _ = umeyama_alignment(src, dst)
    np.testing.assert_allclose(R, R_true, atol=1e-12)
    np.testing.assert_allclose(t, [1.0, 2.0, 3.0], atol=1e-12)
    # two points (N < 3) in 3-D: same
    R2, t2, _ = umeyama_alignment(src[:2], dst[:2])
    np.testing.assert_allclose(R2, R_true, atol=1e-12)
    np.testing.assert_allclose(t2, [1.0, 2.0, 3.0], atol=1e-12)
    # one point: identity, pure translation
    R1, t1, s1 = umeyama_alignment([[1.0, 1.0, 1.0]], [[4.0, 5.0, 6.0]], with_scale=True)
    np.testing.assert_array_equal(R1, np.eye(3))
    np.testing.assert_array_equal(t1, [3.0, 4.0, 5.0])
    assert s1 == 1.0
    # 2-D collinear is not degenerate (rank >= k - 1)
    R2d, _, _ = umeyama_alignment(src[:, :2], dst[:, :2])
    np.testing.assert_allclose(R2d, R_true[:2, :2], atol=1e-12)
    with pytest.raises(ValueError, match="at least one"):
        umeyama_alignment(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError, match="both be"):
        umeyama_alignment(np.zeros((3, 3)), np.zeros((3, 2)))


# ----------------------------------------------------------------------------------------------- APE


def test_ape_of_rigidly_moved_copy_is_zero() -> None:
    rng = np.random.default_rng(5)
    stamps = np.arange(50) * 0.1
    gt = rng.normal(0.0, 3.0, (50, 3)).cumsum(axis=0)
    R = _random_rotation(rng)
    est = gt @ R.T + np.array([10.0, -4.0, 2.0])
    res = ape_rmse(_traj(stamps, gt), _traj(stamps, est))
    assert res.n == 50
    assert res.rmse == pytest.approx(0.0, abs=1e-9)
    assert res.max == pytest.approx(0.0, abs=1e-9)
    # R maps the estimate back onto the reference
    np.testing.assert_allclose(res.R, R.T, atol=1e-9)


def test_ape_every_other_point_shifted_hand_computed() -> None:
    d = 0.4
    stamps = np.arange(6, dtype=float)
    ref = np.column_stack([stamps, np.zeros(6), np.zeros(6)])
    est = ref.copy()
    est[1::2, 0] += d  # odd points shifted by +d along the line
    # Unaligned: errors 0, d, 0, d, 0, d -> RMSE d/sqrt(2), mean d/2, max d.
    raw = ape_rmse(_traj(stamps, ref), _traj(stamps, est), align=False)
    assert raw.rmse == pytest.approx(d / math.sqrt(2.0), abs=1e-12)
    assert raw.mean == pytest.approx(d / 2, abs=1e-12)
    assert raw.max == pytest.approx(d, abs=1e-12)
    # Aligned: the best translation is -d/2 along the line, every error becomes d/2.
    aligned = ape_rmse(_traj(stamps, ref), _traj(stamps, est))
    assert aligned.rmse == pytest.approx(d / 2, abs=1e-12)
    assert aligned.max == pytest.approx(d / 2, abs=1e-12)
    np.testing.assert_allclose(aligned.t, [-d / 2, 0.0, 0.0], atol=1e-12)


def test_ape_square_with_diagonal_corners_raised_hand_computed() -> None:
    d = 0.3
    ref = np.array([[1.0, 1.0, 0.0], [-1.0, 1.0, 0.0], [-1.0, -1.0, 0.0], [1.0, -1.0, 0.0]])
    est = ref.copy()
    est[[0, 2], 2] += d  # the cross-covariance terms cancel: R = I, t = (0, 0, -d/2)
    res = ape_positions(ref, est)
    np.testing.assert_allclose(res.R, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(res.t, [0.0, 0.0, -d / 2], atol=1e-12)
    assert res.rmse == pytest.approx(d / 2, abs=1e-12)


def test_ape_matches_brute_force_minimisation() -> None:
    rng = np.random.default_rng(9)
    ref = rng.normal(0.0, 4.0, (30, 2))
    est = ref @ _rz(0.4)[:2, :2].T + np.array([2.0, 1.0]) + rng.normal(0.0, 0.3, (30, 2))

    def cost(p: np.ndarray) -> float:
        moved = est @ _rz(p[0])[:2, :2].T + p[1:]
        return float(np.mean(np.sum((ref - moved) ** 2, axis=1)))

    best = min(
        (
            minimize(cost, x0=[a, 0.0, 0.0], method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-14})
            for a in np.linspace(-3.0, 3.0, 7)
        ),
        key=lambda r: r.fun,
    )
    res = ape_positions(ref, est)
    assert res.rmse == pytest.approx(math.sqrt(best.fun), rel=1e-6)


def test_ape_rmse_without_association_is_input_error() -> None:
    ref = _traj([0.0, 1.0], np.zeros((2, 3)))
    est = _traj([5.0, 6.0], np.zeros((2, 3)))
    with pytest.raises(InputError, match="no poses associated"):
        ape_rmse(ref, est)


# ----------------------------------------------------------------------------------------------- association


def test_associate_jittered_stamps() -> None:
    rng = np.random.default_rng(1)
    ref_stamps = np.arange(10, dtype=float)
    jitter = rng.uniform(-0.02, 0.02, 10)
    est_stamps = np.concatenate(
        [
            ref_stamps + jitter,  # est i -> ref i
            [4.5, 12.0],  # too far from every reference stamp
            [3.0 + 0.04],  # second claimant of ref 3, further than est 3 (|jitter| < 0.02)
        ]
    )
    perm = rng.permutation(est_stamps.shape[0])  # unsorted input
    est = _traj(est_stamps[perm], np.zeros((13, 3)))
    ref = _traj(ref_stamps, np.zeros((10, 3)))
    idx_ref, idx_est = associate(ref, est, max_diff_s=0.05)
    assert idx_ref.dtype == np.int64 and idx_est.dtype == np.int64
    np.testing.assert_array_equal(idx_ref, np.arange(10))
    np.testing.assert_array_equal(perm[idx_est], np.arange(10))
    assert len(set(idx_est.tolist())) == 10
    # tighter tolerance drops the jittered pairs beyond it
    idx_ref2, _ = associate(ref, est, max_diff_s=0.01)
    np.testing.assert_array_equal(idx_ref2, np.flatnonzero(np.abs(jitter) <= 0.01))
    empty_ref, empty_est = associate(ref, _traj([], np.zeros((0, 3))))
    assert empty_ref.shape == (0,) and empty_est.shape == (0,)


def test_interpolate_poses() -> None:
    traj = _traj([0.0, 2.0, 4.0], [[0, 0, 0], [2, 4, 0], [2, 4, 8]])
    out = interpolate_poses(traj, [1.0, 3.0, 4.0, 4.03, -0.1, 5.0], max_diff_s=0.05)
    np.testing.assert_allclose(out[:4], [[1, 2, 0], [2, 4, 4], [2, 4, 8], [2, 4, 8]])
    assert np.isnan(out[4:]).all()


# ----------------------------------------------------------------------------------------------- Hausdorff


def test_hausdorff_hand_made_sets() -> None:
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    with_outlier = np.vstack([square, [[1.0, 4.0]]])  # 3 m above the corner (1, 1)
    assert hausdorff(square, with_outlier) == pytest.approx(3.0, abs=1e-12)
    assert hausdorff(with_outlier, square) == pytest.approx(3.0, abs=1e-12)
    # asymmetric: A -> B is 1, B -> A is 4; the symmetric distance is the larger
    a = np.array([[0.0, 0.0], [1.0, 0.0]])
    b = np.array([[0.0, 0.0], [5.0, 0.0]])
    assert hausdorff(a, b) == pytest.approx(4.0, abs=1e-12)
    assert hausdorff(square, square) == 0.0
    with pytest.raises(ValueError, match="non-empty"):
        hausdorff(np.zeros((0, 2)), square)


def test_hausdorff_matches_brute_force() -> None:
    rng = np.random.default_rng(4)
    a = rng.normal(size=(57, 3))
    b = rng.normal(size=(31, 3)) + 0.5
    dist = cdist(a, b)
    expected = max(dist.min(axis=1).max(), dist.min(axis=0).max())
    assert hausdorff(a, b) == pytest.approx(expected, abs=1e-12)


# ----------------------------------------------------------------------------------------------- maps


def _circle_gt(n: int = 201, duration: float = 20.0, z_amp: float = 0.0) -> Trajectory:
    t = np.linspace(0.0, duration, n)
    ang = 2.0 * math.pi * t / duration
    pos = np.column_stack([10.0 * np.cos(ang), 10.0 * np.sin(ang), z_amp * np.sin(2 * ang)])
    return _traj(t, pos)


def _map_from_positions(
    stamps: np.ndarray,
    positions: np.ndarray,
    origins: np.ndarray | None = None,
    odometry: np.ndarray | None = None,
    names: dict[int, str] | None = None,
) -> dict[str, Any]:
    n = stamps.shape[0]
    origins = np.zeros(n, dtype=np.int64) if origins is None else origins
    names = names or {0: "s0"}
    pose = np.column_stack([positions, np.zeros(n)])
    snap = {
        "lv_means": np.zeros(n),
        "em_pose": pose,
        "em_template": np.arange(n, dtype=np.int64),
        "em_stamp": stamps,
        "em_origin": origins,
        "em_link_from": np.arange(n - 1, dtype=np.int64),
        "em_link_to": np.arange(1, n, dtype=np.int64),
        "em_link_transform": np.zeros((n - 1, 4)),
        "em_link_dt": np.diff(stamps),
        "em_link_distance": np.linalg.norm(np.diff(positions, axis=0), axis=1),
        "em_link_kind": np.zeros(n - 1, dtype=np.int8),
    }
    sessions = [SessionInfo(name, "0" * 64, 10) for name in names.values()]
    return map_json(
        params={"preset": "test"},
        snapshot=snap,
        sessions=sessions,
        session_name_by_origin=names,
        odometry=odometry,
    )


def test_evaluate_map_planar_rigid_copy() -> None:
    gt = _circle_gt()
    stamps = np.arange(0.35, 20.0, 1.3)  # between ground-truth samples: interpolated
    truth = interpolate_poses(gt, stamps)
    moved = truth @ _rz(0.9).T + np.array([5.0, -3.0, 0.0])
    doc = _map_from_positions(stamps, moved)
    res = evaluate_map(doc, gt)
    assert res["experiences"] == stamps.shape[0]
    assert res["aligned"] == stamps.shape[0]
    assert res["dims"] == 2
    assert res["ape_rmse"] == pytest.approx(0.0, abs=1e-9)
    assert res["odometry_ape_rmse"] is None
    dist = cdist(truth[:, :2], gt.positions_xyz[:, :2])
    expected = max(dist.min(axis=1).max(), dist.min(axis=0).max())
    assert res["hausdorff"] == pytest.approx(expected, abs=1e-9)
    json.dumps(res, allow_nan=False)


def test_evaluate_map_planar_ignores_gt_height_and_uses_odometry_key() -> None:
    gt = _circle_gt(z_amp=2.0)
    stamps = np.arange(0.5, 20.0, 1.0)
    truth = interpolate_poses(gt, stamps)
    flat = truth.copy()
    flat[:, 2] = 0.0
    # odometry at the ground-truth stamps: a rigid copy scaled by 1.1 (drift)
    odo_xyz = gt.positions_xyz.copy() * 1.1
    odo_xyz[:, 2] = 0.0
    odometry = np.column_stack([gt.stamps_s, odo_xyz])
    doc = _map_from_positions(stamps, flat, odometry=odometry)
    res = evaluate_map(doc, gt)
    assert res["dims"] == 2
    assert res["ape_rmse"] == pytest.approx(0.0, abs=1e-9)
    # independent path: nearest-stamp association of the same poses (stamps coincide), xy only
    gt_flat = _traj(gt.stamps_s, np.column_stack([gt.positions_xyz[:, :2], np.zeros(len(gt))]))
    expected = ape_rmse(gt_flat, _traj(gt.stamps_s, odo_xyz)).rmse
    assert expected > 0.1
    assert res["odometry_ape_rmse"] == pytest.approx(expected, rel=1e-9)
    assert res["odometry_aligned"] == len(gt)
    # an explicit odometry trajectory wins over the key
    res2 = evaluate_map(doc, gt, odometry=_traj(gt.stamps_s, gt_flat.positions_xyz))
    assert res2["odometry_ape_rmse"] == pytest.approx(0.0, abs=1e-9)


def test_evaluate_map_3d_and_sessions() -> None:
    gt = _circle_gt(z_amp=2.0)
    stamps = np.arange(0.5, 20.0, 1.0)
    truth = interpolate_poses(gt, stamps)
    origins = (np.arange(stamps.shape[0]) % 2).astype(np.int64)
    doc = _map_from_positions(stamps, truth + np.array([0.0, 0.0, 1.0]), origins, names={0: "a", 1: "b"})
    res = evaluate_map(doc, gt)
    assert res["dims"] == 3
    assert res["ape_rmse"] == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(res["alignment"]["translation"], [0.0, 0.0, -1.0], atol=1e-9)
    only_b = evaluate_map(doc, gt, session="b")
    assert only_b["experiences"] == int((origins == 1).sum())
    assert only_b["session"] == "b"
    with pytest.raises(InputError, match="no experience of session 'c'"):
        evaluate_map(doc, gt, session="c")


def test_a_sessions_hausdorff_is_against_the_ground_truth_its_own_experiences_cover() -> None:
    """A merged session made experiences only in its first 8 s (then it drove through another session's
    places): its Hausdorff distance compares them with the ground truth of those 8 s (must: as exact as its
    APE), not with the whole drive (must not: the far side of the circle)."""
    gt = _circle_gt()
    stamps = np.arange(0.5, 20.0, 1.0)
    truth = interpolate_poses(gt, stamps)
    origins = np.where(stamps < 8.0, 1, 0).astype(np.int64)
    doc = _map_from_positions(stamps, truth, origins, names={0: "first", 1: "merged"})
    merged = evaluate_map(doc, gt, session="merged")
    own = truth[origins == 1]
    window = (gt.stamps_s >= 0.5 - 2.0) & (gt.stamps_s <= 7.5 + 2.0)  # within 2 × the 1 s spacing of its own
    dist = cdist(own[:, :2], gt.positions_xyz[window, :2])
    assert merged["hausdorff"] == pytest.approx(max(dist.min(axis=1).max(), dist.min(axis=0).max()), abs=1e-9)
    whole = cdist(own[:, :2], gt.positions_xyz[:, :2])
    assert merged["hausdorff"] < 0.5 * max(whole.min(axis=1).max(), whole.min(axis=0).max())
    # must still: the whole map (no session chosen) is compared with all of the ground truth
    everything = evaluate_map(doc, gt)
    full = cdist(truth[:, :2], gt.positions_xyz[:, :2])
    assert everything["hausdorff"] == pytest.approx(max(full.min(axis=1).max(), full.min(axis=0).max()), abs=1e-9)


def test_evaluate_map_disjoint_times_is_input_error() -> None:
    gt = _circle_gt()
    stamps = np.array([100.0, 101.0, 102.0])
    doc = _map_from_positions(stamps, np.zeros((3, 3)))
    with pytest.raises(InputError, match="no experience stamp falls within"):
        evaluate_map(doc, gt)


def test_plot_writes_png_3d(tmp_path: Path) -> None:
    gt = _circle_gt(z_amp=2.0)
    stamps = np.arange(0.5, 20.0, 1.0)
    doc = _map_from_positions(stamps, interpolate_poses(gt, stamps) + 0.05)
    out = tmp_path / "plot3d.png"
    plot_map_vs_ground_truth(doc, gt, out, title="3-D")
    data = out.read_bytes()
    assert data.startswith(PNG_SIGNATURE) and len(data) > 1000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plot3d.png"]


# ----------------------------------------------------------------------------------------------- CLI


def _write_case(tmp_path: Path) -> tuple[Path, Path]:
    gt = _circle_gt()
    stamps = np.arange(0.25, 20.0, 0.8)
    truth = interpolate_poses(gt, stamps)
    rng = np.random.default_rng(2)
    est = truth @ _rz(-0.5).T + np.array([1.0, 2.0, 0.0])
    est[:, :2] += rng.normal(0.0, 0.1, (stamps.shape[0], 2))
    odo = np.column_stack([gt.stamps_s, gt.positions_xyz * np.array([1.05, 1.0, 0.0])])
    doc = _map_from_positions(stamps, est, odometry=odo)
    map_path = tmp_path / "map.json"
    gt_path = tmp_path / "gt.tum"
    write_map_json(map_path, doc)
    write_tum(gt_path, gt.stamps_s, gt.positions_xyz, gt.quat_xyzw)
    return map_path, gt_path


def test_cli_evaluate_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    map_path, gt_path = _write_case(tmp_path)
    png = tmp_path / "eval.png"
    code = main(["evaluate", str(map_path), "--ground-truth", str(gt_path), "--json", "--plot", str(png)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    result = json.loads(captured.out.strip().splitlines()[-1])
    for key in ("ape_rmse", "odometry_ape_rmse", "hausdorff", "experiences"):
        assert key in result
    assert 0.0 < result["ape_rmse"] < 0.3
    assert result["odometry_ape_rmse"] > 0.0
    assert result["experiences"] == 25
    assert "APE RMSE" in captured.err and "Hausdorff" in captured.err
    data = png.read_bytes()
    assert data.startswith(PNG_SIGNATURE) and len(data) > 0
    # the numbers equal the library's
    from mapserver.formats import read_map_json, read_tum

    lib = evaluate_map(read_map_json(map_path), read_tum(gt_path))
    assert result["ape_rmse"] == pytest.approx(lib["ape_rmse"], rel=1e-12)
    assert result["hausdorff"] == pytest.approx(lib["hausdorff"], rel=1e-12)


def test_cli_evaluate_without_json_prints_nothing_on_stdout(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    map_path, gt_path = _write_case(tmp_path)
    assert main(["evaluate", str(map_path), "--ground-truth", str(gt_path)]) == 0
    captured = capsys.readouterr()
    assert captured.out == ""
    assert "APE RMSE" in captured.err


@pytest.mark.parametrize("which", ["map", "gt"])
def test_cli_evaluate_missing_file_exits_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], which: str
) -> None:
    map_path, gt_path = _write_case(tmp_path)
    if which == "map":
        map_path = tmp_path / "missing.json"
    else:
        gt_path = tmp_path / "missing.tum"
    code = main(["evaluate", str(map_path), "--ground-truth", str(gt_path), "--json"])
    captured = capsys.readouterr()
    assert code == 2
    assert captured.out == ""
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ERROR:") and "not found" in err[0]


def test_cli_evaluate_malformed_tum_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    map_path, gt_path = _write_case(tmp_path)
    lines = gt_path.read_text(encoding="utf-8").splitlines()
    lines[3] = "1.0 2.0 oops"
    gt_path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    assert main(["evaluate", str(map_path), "--ground-truth", str(gt_path)]) == 2
    assert ":4:" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------- place recognition


def _out_and_back() -> tuple[Trajectory, list[list[float]]]:
    """x = t out to 30 m, then back to 0 at 1 m/s; frames every 5 s with a hand-made template record."""
    t = np.linspace(0.0, 60.0, 601)
    x = np.where(t <= 30.0, t, 60.0 - t)
    gt = _traj(t, np.column_stack([x, np.zeros_like(t), np.zeros_like(t)]))
    # frames at t = 0, 5, ..., 60 (x = 0..30..0); t <= 30 create templates 0..6 (template k at x = 5k)
    rows = [[5.0 * k, k, 1] for k in range(7)]
    rows += [
        [35.0, 5, 0],  # x = 25 matches the template made at x = 25 (10 s earlier: not a revisit)
        [40.0, 7, 1],  # x = 20 creates a template (its twin at t = 20 is exactly 20 s earlier: not a revisit)
        [45.0, 3, 0],  # x = 15: template from x = 15, 30 s earlier: recognised
        [50.0, 1, 0],  # x = 10: template from x = 5 (5 m > R' = 3): not recognised, not false (5 m is not > 5)
        [55.0, 0, 0],  # x = 5: template from x = 0 (5 m): not recognised
        [60.0, 6, 0],  # x = 0: template from x = 30 (30 m): false match
    ]
    return gt, rows


def test_place_recognition_hand_computed() -> None:
    gt, rows = _out_and_back()
    result = place_recognition(rows, gt, RecognitionSettings(1.0, 20.0, 3.0, 5.0))
    assert result["revisit_frames"] == 4  # t = 45, 50, 55, 60
    assert result["revisit_matched"] == 1
    assert result["revisit_match_rate"] == pytest.approx(0.25)
    assert result["matched_frames"] == 5
    assert result["false_matches"] == 1
    assert result["false_match_rate"] == pytest.approx(0.2)
    assert result["frames_evaluated"] == 13
    looser = place_recognition(rows, gt, RecognitionSettings(1.0, 20.0, 5.0, 40.0))
    assert looser["revisit_matched"] == 3 and looser["false_matches"] == 0


def test_place_recognition_skips_frames_outside_the_ground_truth() -> None:
    gt, rows = _out_and_back()
    result = place_recognition([*rows, [99.0, 2, 0]], gt)
    assert result["frames_evaluated"] == 13
    none = place_recognition([[0.0, 0, 1], [1.0, 0, 0]], gt)
    assert none["revisit_frames"] == 0 and none["revisit_match_rate"] is None
    assert none["matched_frames"] == 1 and none["false_match_rate"] == 0.0


def test_cli_evaluate_reports_recognition_and_height(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    gt, rows = _out_and_back()
    stamps = np.array([0.0, 20.0, 40.0, 60.0])
    positions = interpolate_poses(gt, stamps) + np.array([0.0, 0.0, 0.1])  # z = 0.1 everywhere: a 3-D map
    doc = _map_from_positions(stamps, positions)
    doc["frames"] = rows
    map_path, gt_path = tmp_path / "m.json", tmp_path / "gt.tum"
    write_map_json(map_path, doc)
    write_tum(gt_path, gt.stamps_s, gt.positions_xyz, gt.quat_xyzw)
    code = main(["evaluate", str(map_path), "--ground-truth", str(gt_path), "--json", "--match-radius", "5",
                 "--false-radius", "40"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    result = json.loads(captured.out.strip().splitlines()[-1])
    assert result["revisit_frames"] == 4 and result["revisit_match_rate"] == pytest.approx(0.75)
    assert result["false_match_rate"] == 0.0
    assert result["recognition_settings"]["match_radius"] == 5.0
    assert result["dims"] == 3 and result["ape_z_rmse"] == pytest.approx(0.0, abs=1e-9)  # z offset aligned away
    assert "revisits: 4 frames, 3 recognised (75.0 %)" in captured.err
    code = main(["evaluate", str(map_path), "--ground-truth", str(gt_path), "--revisit-gap", "-1"])
    assert code == 2 and "--revisit-gap" in capsys.readouterr().err

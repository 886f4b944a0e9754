"""Relative pose error (mapserver.evaluation.rpe): pairs by path length, drift by hand, invariance to rigid motion."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from mapserver.evaluation.rpe import pairs_by_path, relative_pose_error, yaw_rotations


def test_pairs_close_where_the_path_reaches_the_segment_length() -> None:
    # steps of 0.4 m: 0.4, 0.8, 1.2 (≥ 1: pair 0-3), then 0.4, 0.8, 1.2 again (pair 3-6); 7, 8 leave 0.8
    positions = np.column_stack([np.arange(9) * 0.4, np.zeros(9), np.zeros(9)])
    first, last = pairs_by_path(positions, 1.0)
    assert first.tolist() == [0, 3] and last.tolist() == [3, 6]
    # a step landing exactly on the length closes the pair (≥, as evo)
    first, last = pairs_by_path(np.column_stack([np.arange(5) * 0.5, np.zeros(5), np.zeros(5)]), 1.0)
    assert first.tolist() == [0, 2] and last.tolist() == [2, 4]
    # a path shorter than the length gives no pair
    assert pairs_by_path(positions, 100.0)[0].size == 0


def test_a_ten_percent_scale_error_drifts_a_tenth_of_each_segment() -> None:
    # the reference drives 10 m straight along x in 0.5 m steps; the estimate reads every step 10 % long
    n = 21
    ref = np.column_stack([np.arange(n) * 0.5, np.zeros(n), np.zeros(n)])
    est = ref * 1.1
    heading = yaw_rotations(np.zeros(n))
    result = relative_pose_error(ref, heading, est, heading, 1.0)
    assert result.pairs == 10
    assert result.trans_rmse == pytest.approx(0.1, abs=1e-12)  # 1 m segments, 0.1 m too long each
    assert result.trans_max == pytest.approx(0.1, abs=1e-12) and result.rot_rmse_deg == pytest.approx(0.0, abs=1e-9)
    # must not: the same trajectory as its own estimate has no error
    assert relative_pose_error(ref, heading, ref, heading, 1.0).trans_rmse == pytest.approx(0.0, abs=1e-12)


def test_a_heading_error_turns_the_segment() -> None:
    # the estimate believes the robot faced 10° left all along: its relative poses are the reference's, so
    # no error (RPE ignores a constant offset) — but a heading that drifts 10° per metre shows as 10° per pair
    n = 11
    ref = np.column_stack([np.arange(n) * 1.0, np.zeros(n), np.zeros(n)])
    still = yaw_rotations(np.zeros(n))
    offset = yaw_rotations(np.full(n, math.radians(10)))
    rotated = ref @ Rotation.from_euler("z", 10, degrees=True).as_matrix().T
    assert relative_pose_error(ref, still, rotated, offset, 1.0).trans_rmse == pytest.approx(0.0, abs=1e-12)
    drifting = yaw_rotations(np.radians(10.0 * np.arange(n)))
    result = relative_pose_error(ref, still, ref, drifting, 1.0)
    assert result.rot_rmse_deg == pytest.approx(10.0, abs=1e-9)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), yaw=st.floats(-math.pi, math.pi), shift=st.floats(-100, 100))
def test_rpe_is_unchanged_by_a_rigid_motion_of_the_estimate(seed: int, yaw: float, shift: float) -> None:
    rng = np.random.default_rng(seed)
    n = 40
    ref_yaw = np.cumsum(rng.normal(0, 0.2, n))
    ref = np.cumsum(np.column_stack([np.cos(ref_yaw), np.sin(ref_yaw), np.zeros(n)]) * 0.5, axis=0)
    est_yaw = ref_yaw + rng.normal(0, 0.05, n)
    est = ref + rng.normal(0, 0.1, (n, 3)) * [1, 1, 0]
    before = relative_pose_error(ref, yaw_rotations(ref_yaw), est, yaw_rotations(est_yaw), 2.0)
    turn = Rotation.from_euler("z", yaw)
    moved = turn.apply(est) + np.array([shift, -shift, 0.0])
    after = relative_pose_error(ref, yaw_rotations(ref_yaw), moved, yaw_rotations(est_yaw + yaw), 2.0)
    assert after.pairs == before.pairs > 0
    assert after.trans_rmse == pytest.approx(before.trans_rmse, abs=1e-9)
    assert after.rot_rmse_deg == pytest.approx(before.rot_rmse_deg, abs=1e-7)

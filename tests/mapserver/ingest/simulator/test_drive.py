"""Simulated drives: exact odometry without noise, drift with it, ground truth and camera stamps."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapserver.ingest.odometry import OdometryState, integrate_twist
from mapserver.ingest.simulator import DriveSpec, Noise, Rates, routes, simulate_drive
from mapserver.ingest.simulator.drive import Trajectory, body_twist, integrate

QUIET = Noise(
    lateral_m=0.1, speed_variation=0.1, scale_error=0.0, yaw_bias=0.0, speed_noise=0.0, yaw_noise=0.0, gain=0.0
)
LOOP = routes.rounded_rectangle((0.0, 0.0), 12.0, 8.0, 2.0)


def _in_world(drive_true: np.ndarray, odom: np.ndarray) -> np.ndarray:
    """Odometry poses moved into the world frame by the true start pose."""
    x0, y0, _, yaw0 = drive_true[0]
    c, s = math.cos(yaw0), math.sin(yaw0)
    return np.column_stack([x0 + c * odom[:, 0] - s * odom[:, 1], y0 + s * odom[:, 0] + c * odom[:, 1]])


def test_noise_free_odometry_integrates_to_the_ground_truth() -> None:
    drive = simulate_drive(DriveSpec(LOOP, 0.0, LOOP.length, 0.5), QUIET, Rates(), 0, np.random.default_rng(4))
    assert np.abs(_in_world(drive.true_poses, drive.odom_poses) - drive.true_poses[:, :2]).max() < 1e-9
    gt = np.array([[g.x, g.y] for g in drive.ground_truth])
    assert np.array_equal(gt, drive.true_poses[:, :2])
    # ... and the reader's zero-order-hold integration of the published twist gives the same displacement
    states = [OdometryState(o.stamp_ns, o.x, o.y, o.z, o.yaw, o.vx, o.vy, o.vz, o.wz) for o in drive.odometry]
    motion = integrate_twist(states, drive.odometry[0].stamp_ns, drive.odometry[-1].stamp_ns)
    end = drive.odom_poses[-1]
    assert (motion.dx, motion.dy, motion.dyaw) == pytest.approx((end[0], end[1], end[3]), abs=1e-9)


def test_noisy_odometry_drifts_so_the_loop_does_not_close() -> None:
    big = routes.rounded_rectangle((0.0, 0.0), 24.0, 14.0, 4.0)  # the loop scenario's lap
    drive = simulate_drive(DriveSpec(big, 0.0, big.length, 0.5), Noise(), Rates(), 0, np.random.default_rng(4))
    world = _in_world(drive.true_poses, drive.odom_poses)
    true_gap = np.linalg.norm(drive.true_poses[-1, :2] - drive.true_poses[0, :2])
    odo_gap = np.linalg.norm(world[-1] - world[0])
    assert true_gap < 0.5  # one lap: the vehicle is back (up to its lateral wander)
    assert odo_gap > 1.5  # the odometry thinks it is metres away
    assert set(drive.errors) == {"scale_error", "yaw_bias", "vz_bias"}
    assert abs(drive.errors["yaw_bias"]) == Noise().yaw_bias


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(0.0, 1.5), st.floats(-0.2, 0.2), st.floats(-0.1, 0.1), st.floats(-1.5, 1.5)),
                min_size=1, max_size=20))
def test_body_twist_inverts_integrate(twists: list[tuple[float, float, float, float]]) -> None:
    tw = np.asarray(twists)
    poses = integrate(tw, 0.1)
    assert np.allclose(body_twist(poses, 0.1), tw, atol=1e-9)


def test_camera_stamps_rates_and_session_length() -> None:
    rates = Rates(camera_hz=2.0, odom_hz=20.0, camera_offset_s=0.05)
    spec = DriveSpec(LOOP, 3.0, 20.0, 0.5)
    drive = simulate_drive(spec, QUIET, rates, 7_000_000_000, np.random.default_rng(1))
    stamps = np.diff([o.stamp_ns for o in drive.odometry])
    assert np.all(stamps == 50_000_000)
    assert drive.frame_stamps_ns[0] == 7_050_000_000
    assert np.all(np.diff(drive.frame_stamps_ns) == 500_000_000)
    assert drive.frame_stamps_ns[-1] <= drive.odometry[-1].stamp_ns
    travelled = np.sum(np.linalg.norm(np.diff(drive.true_poses[:, :2], axis=0), axis=1))
    assert travelled == pytest.approx(20.0, rel=0.02)  # lateral wander adds a little
    assert np.linalg.norm(drive.true_poses[0, :2] - LOOP.position(3.0)) < 0.4


def test_initial_turn_rotates_the_start_heading() -> None:
    base = Trajectory(DriveSpec(LOOP, 0.0, 5.0, 0.5), QUIET, np.random.default_rng(2))
    turned = Trajectory(DriveSpec(LOOP, 0.0, 5.0, 0.5, turn_deg=90.0), QUIET, np.random.default_rng(2))
    assert turned.turn_s == pytest.approx(math.pi / 2 / 0.3)  # 90° at 0.3 rad/s
    start, during = turned.pose([0.0, turned.turn_s / 2])
    assert start[3] == pytest.approx(base.pose(0.0)[0, 3] - math.pi / 2, abs=1e-9)
    assert during[3] == pytest.approx(base.pose(0.0)[0, 3] - math.pi / 4, abs=1e-9)
    assert np.allclose(start[:2], during[:2])  # turning on the spot
    tau = np.linspace(0.0, base.drive_s, 7)
    assert np.allclose(turned.pose(turned.turn_s + tau), base.pose(tau), atol=1e-9)  # then the same drive


def test_depth_profile_and_vertical_drift() -> None:
    def depth(s: np.ndarray) -> np.ndarray:
        return -1.0 - 0.1 * np.asarray(s)

    noise = Noise(scale_error=0.0, yaw_bias=0.0, speed_noise=0.0, yaw_noise=0.0, vz_bias=0.01)
    drive = simulate_drive(DriveSpec(LOOP, 0.0, 5.0, 0.5, depth=depth), noise, Rates(), 0, np.random.default_rng(3))
    assert drive.true_poses[0, 2] == pytest.approx(-1.0, abs=1e-9)
    assert drive.true_poses[-1, 2] == pytest.approx(-1.5, abs=0.01)  # the last sample is up to 0.1 s short
    duration = (drive.odometry[-1].stamp_ns - drive.odometry[0].stamp_ns) * 1e-9
    drift = drive.odom_poses[-1, 2] - (drive.true_poses[-1, 2] - drive.true_poses[0, 2])
    assert abs(drive.errors["vz_bias"]) == 0.01
    assert drift == pytest.approx(drive.errors["vz_bias"] * duration, abs=1e-9)

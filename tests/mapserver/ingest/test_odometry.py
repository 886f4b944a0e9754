from __future__ import annotations

import math

import numpy as np
import pytest

from core.angles import wrap_angle_exact
from mapserver.ingest.odometry import (
    OdometryState,
    OdometryTrack,
    arc_increment,
    difference_poses,
    integrate_twist,
    interpolate_pose,
    make_state,
    relative_motion,
)
from tests.mapserver.ingest.conftest import arc_pose

S = 1_000_000_000


def twist_state(stamp_ns: int, v: float, w: float, u: float = 0.0, vz: float = 0.0) -> OdometryState:
    return OdometryState(stamp_ns, 0.0, 0.0, 0.0, 0.0, v, u, vz, w)


def test_hand_computed_arc() -> None:
    # v = 1 m/s, ω = 0.5 rad/s for 0.4 s: θ = 0.2 rad, dx = sin(0.2)/0.5, dy = (1 - cos 0.2)/0.5.
    # sin(0.2) = 0.19866933079506122, cos(0.2) = 0.9800665778412416 (by series / table)
    m = integrate_twist([twist_state(0, 1.0, 0.5)], 0, 400_000_000)
    assert m.dx == pytest.approx(0.39733866159012243, abs=1e-12)
    assert m.dy == pytest.approx(0.03986684431751676, abs=1e-12)
    assert m.dz == 0.0
    assert m.dyaw == pytest.approx(0.2, abs=1e-15)
    assert m.dt == pytest.approx(0.4, abs=1e-15)


def test_result_independent_of_message_placement() -> None:
    rng = np.random.default_rng(1)
    reference = integrate_twist([twist_state(0, 1.0, 0.5, u=0.1, vz=0.2)], S, 3 * S)
    for _ in range(5):
        stamps = sorted({0, *rng.integers(1, 3 * S, size=7).tolist()})
        states = [twist_state(int(t), 1.0, 0.5, u=0.1, vz=0.2) for t in stamps]
        m = integrate_twist(states, S, 3 * S)
        for a, b in zip(
            (m.dx, m.dy, m.dz, m.dyaw),
            (reference.dx, reference.dy, reference.dz, reference.dyaw),
            strict=True,
        ):
            assert a == pytest.approx(b, abs=1e-12)
    assert reference.dyaw == pytest.approx(1.0)
    assert reference.dz == pytest.approx(0.4)
    # without lateral speed it is the closed-form arc, whatever the start time
    m = integrate_twist([twist_state(0, 1.0, 0.5)], S, 3 * S)
    assert (m.dx, m.dy, m.dyaw) == pytest.approx(arc_pose(2.0, 1.0, 0.5), abs=1e-12)


def test_zero_order_hold_piecewise() -> None:
    # 1 m/s straight for 0.5 s, then turning in place at 1 rad/s for 0.5 s, then 2 m/s straight.
    states = [twist_state(0, 1.0, 0.0), twist_state(S // 2, 0.0, 1.0), twist_state(S, 2.0, 0.0)]
    m = integrate_twist(states, 0, 3 * S // 2)
    assert m.dx == pytest.approx(0.5 + 1.0 * math.cos(0.5))
    assert m.dy == pytest.approx(1.0 * math.sin(0.5))
    assert m.dyaw == pytest.approx(0.5)


def test_at_rest_before_first_message_and_hold_after_last() -> None:
    m = integrate_twist([twist_state(S, 1.0, 0.0)], 0, 2 * S)
    assert m.dx == pytest.approx(1.0)
    assert m.dt == pytest.approx(2.0)
    assert integrate_twist([], 0, S).dx == 0.0


def test_small_yaw_rate_limit_is_continuous() -> None:
    for w in (0.0, 1e-9, 1e-6, 2.5e-4, 1e-3):
        dx, dy, _dz, dth = arc_increment(2.0, 0.3, 0.0, w, 0.4)
        if w == 0.0:
            assert (dx, dy) == (0.8, 0.12)
        else:
            one_minus_cos = 2.0 * math.sin(w * 0.2) ** 2  # 1 - cos(0.4 w) without cancellation
            exact_dx = (math.sin(w * 0.4) * 2.0 - one_minus_cos * 0.3) / w
            exact_dy = (one_minus_cos * 2.0 + math.sin(w * 0.4) * 0.3) / w
            assert dx == pytest.approx(exact_dx, abs=1e-12)
            assert dy == pytest.approx(exact_dy, abs=1e-12)
        assert dth == pytest.approx(w * 0.4)


def test_empty_or_backwards_interval() -> None:
    m = integrate_twist([twist_state(0, 1.0, 0.0)], S, S)
    assert (m.dx, m.dt) == (0.0, 0.0)
    assert integrate_twist([twist_state(0, 1.0, 0.0)], 2 * S, S).dt == 0.0


def test_make_state_rotates_body_twist_into_heading_frame() -> None:
    # pitched down by 30° about y (ROS: +pitch turns x towards -z), heading 90°
    pitch, yaw = math.radians(30), math.pi / 2
    cy, sy, cp, sp = math.cos(yaw / 2), math.sin(yaw / 2), math.cos(pitch / 2), math.sin(pitch / 2)
    q = (-sy * sp, cy * sp, sy * cp, cy * cp)  # q_yaw * q_pitch as (x, y, z, w)
    state = make_state(5, (1.0, 2.0, 3.0), q, linear=(1.0, 0.0, 0.0), angular=(0.0, 0.0, 0.5))
    assert state.yaw == pytest.approx(yaw)
    assert state.forward == pytest.approx(math.cos(pitch))
    assert state.lateral == pytest.approx(0.0, abs=1e-12)
    assert state.vertical == pytest.approx(-math.sin(pitch))
    assert state.yaw_rate == pytest.approx(0.5 * math.cos(pitch))


def test_identity_and_zero_quaternion_leave_twist_as_is() -> None:
    for q in ((0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0, 0.0)):
        s = make_state(0, (0, 0, 0), q, (1.0, 0.2, 0.1), (0.0, 0.0, 0.3))
        assert (s.forward, s.lateral, s.vertical, s.yaw_rate) == pytest.approx((1.0, 0.2, 0.1, 0.3))


def test_interpolate_pose_wraps_yaw() -> None:
    a = OdometryState(0, 0.0, 0.0, 0.0, math.pi - 0.1)
    b = OdometryState(S, 2.0, 4.0, 1.0, -math.pi + 0.1)
    x, y, z, yaw = interpolate_pose([a, b], S // 2)
    assert (x, y, z) == pytest.approx((1.0, 2.0, 0.5))
    assert abs(wrap_angle_exact(yaw - math.pi)) < 1e-12
    assert interpolate_pose([a, b], -5) == a.pose
    assert interpolate_pose([a, b], 2 * S) == b.pose


def test_relative_motion_in_previous_heading_frame() -> None:
    m = relative_motion((1.0, 1.0, 0.0, math.pi / 2), (1.0, 3.0, 0.5, math.pi), 2.0)
    assert (m.dx, m.dy, m.dz, m.dyaw, m.dt) == pytest.approx((2.0, 0.0, 0.5, math.pi / 2, 2.0))


def test_pose_differencing_matches_twist_on_arc() -> None:
    rate = 50
    states_pose, states_twist = [], []
    for i in range(60):
        stamp = i * S // rate
        x, y, yaw = arc_pose(stamp * 1e-9, 1.0, 0.5)
        states_pose.append(OdometryState(stamp, x, y, 0.0, wrap_angle_exact(yaw)))
        states_twist.append(OdometryState(stamp, x, y, 0.0, yaw, 1.0, 0.0, 0.0, 0.5))
    for t0, t1 in ((0, 4 * S // 10), (S // 10, 7 * S // 10), (2 * S // 10, S)):
        a = difference_poses(states_pose, t0, t1)
        b = integrate_twist(states_twist, t0, t1)
        assert (a.dx, a.dy, a.dz, a.dyaw, a.dt) == pytest.approx((b.dx, b.dy, b.dz, b.dyaw, b.dt), abs=1e-9)


def test_track_stays_bounded_and_matches_batch() -> None:
    states = [twist_state(i * S // 100, 1.0 + 0.01 * i, 0.2) for i in range(1000)]
    track = OdometryTrack("twist")
    frames = list(range(0, 10 * S, S // 7))
    total_dx_stream, total_dx_batch, peak = 0.0, 0.0, 0
    it = iter(states)
    prev = frames[0]
    for t in frames[1:]:
        while not track.covers(t):
            s = next(it, None)
            if s is None:
                break
            track.push(s)
        peak = max(peak, len(track.states))
        total_dx_stream += track.motion(prev, t).dx
        total_dx_batch += integrate_twist(states, prev, t).dx
        prev = t
    assert total_dx_stream == pytest.approx(total_dx_batch, abs=1e-12)
    assert peak <= 20


def test_track_drops_backwards_stamps() -> None:
    track = OdometryTrack("pose")
    track.push(OdometryState(10, 0, 0, 0, 0))
    track.push(OdometryState(5, 9, 9, 9, 0))
    assert len(track.states) == 1 and track.dropped == 1

"""4-DoF pose algebra and yaw ↔ quaternion: hand-computed cases and invariants (hypothesis)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.angles import wrap_angle
from core.se3 import (
    alignment,
    compose,
    compose_step,
    from_matrix,
    inverse,
    quaternion_from_yaw,
    quaternions_from_yaws,
    relative,
    relative_step,
    to_matrix,
    turn_step,
    yaw_from_quaternion,
    yaw_of_unit_quaternion,
)

coordinate = st.floats(-50.0, 50.0, allow_nan=False)
angle = st.floats(-math.pi, math.pi, allow_nan=False)
pose = st.tuples(coordinate, coordinate, coordinate, angle).map(np.array)


def _close(a: np.ndarray, b: np.ndarray, atol: float = 1e-9) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return bool(np.allclose(a[..., :3], b[..., :3], atol=atol)) and bool(
        np.all(np.abs(wrap_angle(a[..., 3] - b[..., 3])) <= atol)
    )


def test_compose_by_hand() -> None:
    # a robot at (1, 2, 3) facing +y moves 2 m forward and 1 m up, turning 90° more
    a = np.array([1.0, 2.0, 3.0, math.pi / 2])
    b = np.array([2.0, 0.0, 1.0, math.pi / 2])
    assert compose(a, b) == pytest.approx([1.0, 4.0, 4.0, math.pi])


def test_inverse_by_hand() -> None:
    a = np.array([1.0, 0.0, 2.0, math.pi / 2])
    # the origin seen from a: 1 m behind-left... x_body = -(cos·1 + sin·0) = 0, y_body = -(-sin·1) = 1
    assert inverse(a) == pytest.approx([0.0, 1.0, -2.0, -math.pi / 2])


def test_alignment_90_degrees_by_hand() -> None:
    # the partial map saw the place at (2, 0) heading 0; the loaded map has it at (0, 5) heading 90°
    partial = np.array([2.0, 0.0, 0.0, 0.0])
    loaded = np.array([0.0, 5.0, 1.0, math.pi / 2])
    T = alignment(loaded, partial)
    assert pytest.approx([0.0, 3.0, 1.0, math.pi / 2]) == T
    # a partial point 1 m further along the partial x axis is 1 m further along the loaded y axis
    assert compose(T, np.array([3.0, 0.0, 0.0, 0.0])) == pytest.approx([0.0, 6.0, 1.0, math.pi / 2])


def test_matrix_by_hand() -> None:
    m = to_matrix(np.array([1.0, 2.0, 3.0, math.pi / 2]))
    assert m == pytest.approx(np.array([[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], dtype=float))


def test_from_matrix_refuses_roll() -> None:
    m = np.eye(4)
    m[1:3, 1:3] = [[0.0, -1.0], [1.0, 0.0]]  # rotation about x
    with pytest.raises(ValueError, match="rotation about z"):
        from_matrix(m)
    with pytest.raises(ValueError, match="4×4"):
        from_matrix(np.eye(3))


def test_bad_shape_is_refused() -> None:
    with pytest.raises(ValueError, match=r"\(x, y, z, yaw\)"):
        compose(np.zeros(3), np.zeros(4))


@settings(max_examples=60, deadline=None)
@given(pose)
def test_inverse_is_two_sided(a: np.ndarray) -> None:
    assert _close(compose(a, inverse(a)), np.zeros(4))
    assert _close(compose(inverse(a), a), np.zeros(4))


@settings(max_examples=60, deadline=None)
@given(pose, pose, pose)
def test_compose_is_associative(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> None:
    assert _close(compose(compose(a, b), c), compose(a, compose(b, c)), atol=1e-7)


@settings(max_examples=60, deadline=None)
@given(pose, pose)
def test_alignment_takes_partial_onto_loaded(loaded: np.ndarray, partial: np.ndarray) -> None:
    assert _close(compose(alignment(loaded, partial), partial), loaded, atol=1e-8)


@settings(max_examples=60, deadline=None)
@given(pose, pose, pose)
def test_relative_poses_are_invariant(T: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    """A link (relative transform) is the same before and after moving both ends by T."""
    assert _close(relative(compose(T, a), compose(T, b)), relative(a, b), atol=1e-7)


@settings(max_examples=60, deadline=None)
@given(pose, pose)
def test_matrix_product_is_composition(a: np.ndarray, b: np.ndarray) -> None:
    assert to_matrix(compose(a, b)) == pytest.approx(to_matrix(a) @ to_matrix(b), abs=1e-8)
    assert _close(from_matrix(to_matrix(a)), a)


@settings(max_examples=30, deadline=None)
@given(pose, st.lists(pose, min_size=2, max_size=6))
def test_rigid_motion_keeps_distances(T: np.ndarray, points: list[np.ndarray]) -> None:
    p = np.stack(points)
    q = compose(T, p)
    d_before = np.linalg.norm(p[:, None, :3] - p[None, :, :3], axis=2)
    d_after = np.linalg.norm(q[:, None, :3] - q[None, :, :3], axis=2)
    assert d_after == pytest.approx(d_before, abs=1e-8)


# ------------------------------------------------------------------------------ plain-float steps


def test_steps_by_hand() -> None:
    # facing +y at (1, 2, 3): 2 m forward, 1 m left, 1 m up, turning 90° more
    assert compose_step((1.0, 2.0, 3.0, math.pi / 2), (2.0, 1.0, 1.0, math.pi / 2)) == pytest.approx(
        (0.0, 4.0, 4.0, math.pi)
    )
    # from (1, 1) facing +y to (1, 3) facing −x: 2 m forward, heading +90°
    assert relative_step((1.0, 1.0, 0.0, math.pi / 2), (1.0, 3.0, 0.5, math.pi)) == pytest.approx(
        (2.0, 0.0, 0.5, math.pi / 2)
    )
    assert turn_step((1.0, 0.0, 2.0, 0.25), math.pi / 2) == pytest.approx((0.0, 1.0, 2.0, 0.25 + math.pi / 2))


def test_step_headings_are_not_wrapped() -> None:
    assert compose_step((0.0, 0.0, 0.0, 3.0), (0.0, 0.0, 0.0, 3.0))[3] == 6.0
    assert relative_step((0.0, 0.0, 0.0, -3.0), (0.0, 0.0, 0.0, 3.0))[3] == 6.0
    assert turn_step((0.0, 0.0, 0.0, 3.0), 3.0)[3] == 6.0


def test_turn_step_keeps_the_sign_of_zero() -> None:
    """Turning a zero displacement by 180° gives −0.0 where ``(0, 0, 0, yaw) ⊕ step`` would add +0.0."""
    x, y, z, _ = turn_step((0.0, 0.0, -0.0, 0.0), math.pi)
    assert math.copysign(1.0, x) == -1.0 and y == 0.0
    assert math.copysign(1.0, z) == -1.0


@settings(max_examples=60, deadline=None)
@given(pose, pose)
def test_steps_agree_with_the_array_functions(a: np.ndarray, b: np.ndarray) -> None:
    assert _close(np.array(compose_step(a.tolist(), b.tolist())), compose(a, b))
    assert _close(np.array(relative_step(a.tolist(), b.tolist())), relative(a, b), atol=1e-8)
    turned = np.array(turn_step(b.tolist(), float(a[3])))
    assert _close(turned, compose(np.array([0.0, 0.0, 0.0, a[3]]), b))


@settings(max_examples=60, deadline=None)
@given(pose, pose)
def test_relative_step_inverts_compose_step(a: np.ndarray, b: np.ndarray) -> None:
    a_, b_ = a.tolist(), b.tolist()
    assert relative_step(a_, compose_step(a_, b_)) == pytest.approx(b_, abs=1e-9)
    assert compose_step(a_, relative_step(a_, b_)) == pytest.approx(b_, abs=1e-9)


@settings(max_examples=60, deadline=None)
@given(pose, pose, pose)
def test_compose_step_is_associative(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> None:
    a_, b_, c_ = a.tolist(), b.tolist(), c.tolist()
    assert compose_step(compose_step(a_, b_), c_) == pytest.approx(compose_step(a_, compose_step(b_, c_)), abs=1e-7)


# ------------------------------------------------------------------------------ yaw ↔ quaternion

SQRT_HALF = math.sqrt(0.5)


def test_quaternion_by_hand() -> None:
    assert quaternion_from_yaw(0.0) == (0.0, 0.0, 0.0, 1.0)
    qx, qy, qz, qw = quaternion_from_yaw(math.pi / 2)
    assert (qx, qy) == (0.0, 0.0)
    assert qz == pytest.approx(SQRT_HALF, abs=1e-15)
    assert qw == pytest.approx(SQRT_HALF, abs=1e-15)
    assert quaternion_from_yaw(math.pi) == pytest.approx((0.0, 0.0, 1.0, 0.0), abs=1e-15)
    assert yaw_from_quaternion(0.0, 0.0, 1.0, 0.0) == math.pi
    assert yaw_from_quaternion(0.0, 0.0, -1.0, 0.0) == math.pi  # atan2's −π given as π
    assert yaw_from_quaternion(0.0, 0.0, 2.0, 2.0) == pytest.approx(math.pi / 2)  # not normalised: same yaw
    assert yaw_of_unit_quaternion(0.0, 0.0, SQRT_HALF, -SQRT_HALF) == pytest.approx(-math.pi / 2)
    with pytest.raises(ValueError, match="no orientation"):
        yaw_from_quaternion(0.0, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="no orientation"):
        yaw_from_quaternion(0.0, 0.0, math.inf, 0.0)


@given(st.floats(-math.pi, math.pi, exclude_min=True, allow_nan=False))
def test_yaw_quaternion_yaw_round_trip(yaw: float) -> None:
    q = quaternion_from_yaw(yaw)
    assert q[0] == 0.0 and q[1] == 0.0
    assert math.isclose(math.hypot(*q), 1.0, abs_tol=1e-15)
    assert q[3] >= -1e-16  # yaw in (−π, π] → qw ≥ 0
    back = yaw_from_quaternion(*q)
    assert -math.pi < back <= math.pi
    assert abs(float(wrap_angle(back - yaw))) < 1e-12


@given(st.floats(-1e3, 1e3, allow_nan=False), st.floats(0.01, 100.0))
def test_yaw_of_any_angle_and_scale_comes_back_wrapped(yaw: float, scale: float) -> None:
    back = yaw_from_quaternion(*(scale * v for v in quaternion_from_yaw(yaw)))
    assert -math.pi < back <= math.pi
    assert abs(float(wrap_angle(back - yaw))) < 1e-9


@given(st.lists(st.floats(-1e3, 1e3, allow_nan=False), max_size=8))
def test_quaternions_from_yaws_match_the_scalar_form(yaws: list[float]) -> None:
    q = quaternions_from_yaws(np.array(yaws))
    assert q.shape == (len(yaws), 4)
    assert q.reshape(-1).tolist() == pytest.approx([v for y in yaws for v in quaternion_from_yaw(y)], abs=1e-15)

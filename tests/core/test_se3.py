"""4-DoF pose algebra: hand-computed cases and group invariants (hypothesis)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.se3 import alignment, compose, from_matrix, inverse, relative, to_matrix, wrap_angle

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

"""Angle wrapping (core.angles): hand-computed values, the interval ends, and invariants (hypothesis)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from core.angles import TWO_PI, wrap_angle, wrap_angle_below_pi, wrap_angle_exact, wrap_angle_scalar

angles = st.floats(-1e6, 1e6, allow_nan=False)
turns = st.integers(-50, 50)


def test_wrap_by_hand() -> None:
    assert float(wrap_angle(3 * math.pi / 2)) == pytest.approx(-math.pi / 2, abs=1e-15)
    assert float(wrap_angle(-3 * math.pi / 2)) == pytest.approx(math.pi / 2, abs=1e-15)
    assert float(wrap_angle(7.0)) == pytest.approx(7.0 - 2 * math.pi, abs=1e-15)
    assert float(wrap_angle(-7.0)) == pytest.approx(2 * math.pi - 7.0, abs=1e-15)
    assert float(wrap_angle(0.0)) == 0.0
    assert wrap_angle([0.5, 4.0]).tolist() == pytest.approx([0.5, 4.0 - 2 * math.pi], abs=1e-15)
    assert wrap_angle_scalar(7.0) == pytest.approx(7.0 - 2 * math.pi, abs=1e-15)
    assert float(wrap_angle_below_pi(7.0)) == pytest.approx(7.0 - 2 * math.pi, abs=1e-15)
    assert wrap_angle_exact(7.0) == pytest.approx(7.0 - 2 * math.pi, abs=1e-15)
    assert 2 * math.pi == TWO_PI


def test_interval_ends() -> None:
    """π and −π: (−π, π] gives π for both, [−π, π) gives −π for both."""
    for a in (math.pi, -math.pi, 3 * math.pi):
        assert float(wrap_angle(a)) == math.pi
        assert wrap_angle_scalar(a) == math.pi
        assert float(wrap_angle_below_pi(a)) == -math.pi
    assert wrap_angle_exact(math.pi) == math.pi
    assert wrap_angle_exact(-math.pi) == math.pi


def test_the_exact_wrap_keeps_what_adding_pi_rounds_away() -> None:
    """``a + π`` loses the last bits of a small angle; ``math.remainder`` does not (the odometry's wrap)."""
    assert wrap_angle_exact(1e-20) == 1e-20
    assert float(wrap_angle(1e-20)) == 0.0
    assert wrap_angle_scalar(1e-20) == 0.0


@given(a=angles)
def test_wrap_lands_in_its_interval_and_keeps_the_direction(a: float) -> None:
    for w, low_closed in (
        (float(wrap_angle(a)), False),
        (wrap_angle_scalar(a), False),
        (wrap_angle_exact(a), False),
        (float(wrap_angle_below_pi(a)), True),
    ):
        assert (-math.pi <= w < math.pi) if low_closed else (-math.pi < w <= math.pi)
        assert abs(math.remainder(w - a, TWO_PI)) < 1e-9  # whole turns removed, nothing else
        assert math.cos(w) == pytest.approx(math.cos(a), abs=1e-9)
        assert math.sin(w) == pytest.approx(math.sin(a), abs=1e-9)


@given(a=angles)
def test_wrap_is_idempotent(a: float) -> None:
    w = float(wrap_angle(a))
    assert float(wrap_angle(w)) == w
    assert wrap_angle_scalar(wrap_angle_scalar(a)) == wrap_angle_scalar(a)
    b = float(wrap_angle_below_pi(a))
    assert float(wrap_angle_below_pi(b)) == b
    e = wrap_angle_exact(a)
    assert wrap_angle_exact(e) == e


@given(a=st.floats(-math.pi + 1e-6, math.pi - 1e-6), k=turns)
def test_wrap_removes_whole_turns(a: float, k: int) -> None:
    assert float(wrap_angle(a + TWO_PI * k)) == pytest.approx(a, abs=1e-9)
    assert wrap_angle_exact(a + TWO_PI * k) == pytest.approx(a, abs=1e-9)
    assert wrap_angle_exact(a) == a  # inside the interval: untouched


@given(a=st.one_of(angles, st.integers(-1000, 1000).map(lambda k: k * math.pi)))
def test_the_scalar_wrap_gives_the_bits_of_the_array_wrap(a: float) -> None:
    assert wrap_angle_scalar(a) == float(wrap_angle(a))


@given(a=st.one_of(angles, st.integers(-1000, 1000).map(lambda k: k * math.pi)))
def test_the_two_interval_conventions_differ_only_at_the_ends(a: float) -> None:
    w, b = float(wrap_angle(a)), float(wrap_angle_below_pi(a))
    assert w == b or (w, b) == (math.pi, -math.pi)


def test_array_wraps_keep_the_shape() -> None:
    a = np.linspace(-20.0, 20.0, 24).reshape(2, 3, 4)
    assert wrap_angle(a).shape == (2, 3, 4)
    assert wrap_angle_below_pi(a).shape == (2, 3, 4)
    assert wrap_angle(a).dtype == np.float64

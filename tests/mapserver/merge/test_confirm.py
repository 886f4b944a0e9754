"""The confirmation rule on hand-made observations: K agreeing frames along two stored templates."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.se3 import compose
from mapserver.merge import Observation, Streak

# the stored map is the odometry frame turned by 90° and moved by (10, 5)
A_TRUE = np.array([10.0, 5.0, 0.0, math.pi / 2])


def obs(frame: int, x: float, template: int, *, error: float = 0.01, shift: tuple[float, ...] = (0, 0, 0, 0),
        experience: int = 0) -> Observation:
    """The robot at odometry (x, 0) sees stored template ``template`` placed by A_TRUE (+ ``shift``)."""
    odometry = np.array([x, 0.0, 0.0, 0.0])
    seen = compose(A_TRUE, odometry) + np.asarray(shift, dtype=float)
    return Observation(frame, template, experience if experience >= 0 else -1, error, 0.0, 100 + template,
                       odometry, np.zeros(3), seen)


def test_k1_confirms_on_the_first_match() -> None:
    streak = Streak(1, 2.0, 0.5)
    assert streak.add(obs(0, 0.0, 4))
    assert streak.best.frame == 0


def test_k3_needs_three_agreeing_frames_along_two_templates() -> None:
    streak = Streak(3, 2.0, 0.5)
    assert not streak.add(obs(0, 0.0, 4))
    assert not streak.add(obs(1, 0.5, 4))
    assert not streak.add(obs(2, 1.0, 4))  # three frames, but one stored template: one piece of evidence
    assert streak.add(obs(3, 1.5, 5, shift=(0.0, 0.4, 0.0, 0.0)))  # within tolerance of the prediction
    assert len(streak.entries) == 4
    assert streak.pairs() == ((104, 4), (104, 4), (104, 4), (105, 5))


def test_a_match_elsewhere_restarts_the_streak() -> None:
    streak = Streak(3, 2.0, 0.5)
    streak.add(obs(0, 0.0, 4))
    streak.add(obs(1, 0.5, 5))
    # a look-alike 6 m away from where the odometry says the stored map should be seen
    assert not streak.add(obs(2, 1.0, 9, shift=(6.0, 0.0, 0.0, 0.0)))
    assert [e.frame for e in streak.entries] == [2]


def test_a_match_with_the_wrong_heading_restarts_the_streak() -> None:
    streak = Streak(3, 2.0, 0.5)
    streak.add(obs(0, 0.0, 4))
    streak.add(obs(1, 0.5, 5))
    assert not streak.add(obs(2, 1.0, 6, shift=(0.0, 0.0, 0.0, 0.8)))
    assert [e.frame for e in streak.entries] == [2]


def test_the_agreeing_suffix_is_kept() -> None:
    streak = Streak(3, 2.0, 0.5)
    streak.add(obs(0, 0.0, 4, shift=(-3.0, 0.0, 0.0, 0.0)))  # an outlier first
    streak.add(obs(1, 0.5, 5))
    streak.add(obs(2, 1.0, 6))
    assert [e.frame for e in streak.entries] == [1, 2]
    assert streak.add(obs(3, 1.5, 7))


def test_frames_without_stored_geometry_are_neutral() -> None:
    streak = Streak(3, 2.0, 0.5)
    streak.add(obs(0, 0.0, 4))
    assert not streak.add(obs(1, 0.5, 8, experience=-1))
    assert [e.frame for e in streak.entries] == [0]
    streak.add(obs(2, 1.0, 5))
    assert streak.add(obs(3, 1.5, 6))
    assert streak.pairs() == ((104, 4), (108, 8), (105, 5), (106, 6))  # neutral pairs still identified


def test_reset_and_best() -> None:
    streak = Streak(2, 2.0, 0.5)
    streak.add(obs(0, 0.0, 4, error=0.02))
    streak.add(obs(1, 0.5, 5, error=0.01))
    assert streak.confirmed and streak.best.frame == 1
    streak.reset()
    assert not streak.confirmed and streak.entries == []


def test_k_must_be_positive() -> None:
    with pytest.raises(ValueError, match="at least one"):
        Streak(0, 1.0, 0.5)

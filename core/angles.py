"""Angle wrapping: every place of the code base that folds an angle into one turn calls one of these.

The four functions differ only where floating point makes them differ, and each is the exact formula its
callers have always used, so a map computed through them is the same bit for bit:

- :func:`wrap_angle` (arrays) and :func:`wrap_angle_scalar` (one Python float, no numpy overhead) return
  ``remainder(a + π, 2π) − π`` in (−π, π]: a result of −π becomes π (OpenRatSLAM's ``clip_rad_180`` interval).
  The two give the same bits for every finite angle.
- :func:`wrap_angle_below_pi` is the same formula without that last step, in [−π, π) (π becomes −π): the
  relaxation's headings and residuals.
- :func:`wrap_angle_exact` is IEEE ``remainder(a, 2π)``, which rounds nothing (``a + π`` above rounds away the
  last bits of a small angle), in (−π, π]: the odometry read from logs.

``core.compat`` keeps OpenRatSLAM's own loop (``clip_rad_180``: whole turns subtracted one at a time), which
rounds differently again, to match the C++ to the bit.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from core.arrays import FloatArray

TWO_PI = 2.0 * math.pi
"""One turn, 2π (rad)."""


def wrap_angle(angle: npt.ArrayLike) -> FloatArray:
    """Return angles wrapped to (−π, π] as float64: ``remainder(a + π, 2π) − π``, −π given as π."""
    a = np.asarray(angle, dtype=np.float64)
    wrapped = np.remainder(a + math.pi, TWO_PI) - math.pi
    return np.where(wrapped == -math.pi, math.pi, wrapped)


def wrap_angle_scalar(angle: float) -> float:
    """Return one angle wrapped to (−π, π]: the bits of :func:`wrap_angle` without numpy's overhead.

    ``math.fmod`` plus one turn when negative is numpy's ``remainder`` for a positive divisor (a zero result
    may differ in sign, which subtracting π erases).
    """
    wrapped = math.fmod(angle + math.pi, TWO_PI)
    if wrapped < 0.0:
        wrapped += TWO_PI
    wrapped -= math.pi
    return math.pi if wrapped == -math.pi else wrapped


def wrap_angle_below_pi(angle: npt.ArrayLike) -> FloatArray:
    """Return angles wrapped to [−π, π) as float64: ``remainder(a + π, 2π) − π``, π given as −π."""
    return np.remainder(np.asarray(angle, dtype=np.float64) + math.pi, TWO_PI) - math.pi


def wrap_angle_exact(angle: float) -> float:
    """Return one angle wrapped to (−π, π] without rounding: ``math.remainder(a, 2π)``, −π given as π."""
    wrapped = math.remainder(angle, TWO_PI)
    return math.pi if wrapped == -math.pi else wrapped

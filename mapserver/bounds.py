"""The physical bounds every number from outside must keep before it reaches the engine or the store.

One owner for the bounds of issue 61's validation at the edge: the odometry check of a log
(:mod:`mapserver.ingest.odometry`), map imports (:mod:`mapserver.store.import_msr`,
:mod:`mapserver.formats.g2o`), the map JSON and TUM files ``evaluate`` reads (:mod:`mapserver.formats`) and the
REST API's query values (``mapserver.api``) all take their limits from here, and ``GET /v1/limits`` lists them.

* :data:`MAX_POSITION_M`: a coordinate (|x|, |y|, |z|) of a pose, and the length of a link (1e8 m; the
  Earth's scale is 1e7 m);
* :data:`MAX_SPEED_M_S`: the speed of an odometry twist, and of a frame's motion over its dt (1000 m/s);
* :data:`MAX_YAW_RATE_RAD_S`: the yaw rate of an odometry twist (100 rad/s; a gyroscope's range is ~35 rad/s);
* :data:`MAX_ANGLE_RAD`: an angle (a heading, a link's turn) as a file states it (1e6 rad, some 160,000 turns:
  angles may come unwrapped, but beyond this float64 resolves an angle no better than 1e-10 rad);
* :data:`MAX_TIME_S`: a stamp or a duration in seconds (1e10 s; ROS 1 stamps end at 2³² s ≈ 4.3e9 s);
* :data:`MAX_BAD_FRACTION`: dropped odometry messages (of the topic's) or frame motions (of the frames)
  above this share refuse the log (5 %);
* :data:`MAX_QUERY_COORDINATE_M`: a coordinate of a REST query (a point, a bounding box; 1e12 m);
* :data:`MAX_TEMPLATE_VALUE`: a value of an imported view template, an image intensity (1e6; OpenRatSLAM's lie in
  0 … 1, a 16-bit camera's below 65536).

A value outside its bound, or not finite (NaN, ±inf), is refused where it enters; :func:`value_problem` and
:func:`first_out_of_bounds` say why in words shared by every caller.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

MAX_POSITION_M = 1e8
MAX_SPEED_M_S = 1e3
MAX_YAW_RATE_RAD_S = 1e2
MAX_ANGLE_RAD = 1e6
MAX_TIME_S = 1e10
MAX_BAD_FRACTION = 0.05
MAX_QUERY_COORDINATE_M = 1e12
MAX_TEMPLATE_VALUE = 1e6


def _show(value: float) -> str:
    """Return ``value`` short (``1e+300``) when that reads back exactly, else in full (``-100000000.5``)."""
    short = f"{value:g}"
    return short if float(short) == value else repr(value)


def value_problem(value: float, bound: float, unit: str, *, minimum: float | None = None) -> str | None:
    """Return why ``value`` is refused (not finite, beyond ±``bound`` or below ``minimum``), None when it fits.

    The reason reads ``"is not finite (nan)"``, ``"is 1e+300, beyond ±1e+08 m"`` or ``"is -1, below 0 s"``
    and is meant to follow the name of the field.
    """
    if not math.isfinite(value):
        return f"is not finite ({value!r})"
    if minimum is not None and value < minimum:
        return f"is {_show(value)}, below {minimum:g} {unit}".rstrip()
    if abs(value) > bound:
        return f"is {_show(value)}, beyond ±{bound:g} {unit}".rstrip()
    return None


def first_out_of_bounds(
    values: npt.ArrayLike, bound: float, unit: str, *, minimum: float | None = None
) -> tuple[int, str] | None:
    """Return (flat index, reason) of the first value of ``values`` that :func:`value_problem` refuses, or None."""
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    low = -bound if minimum is None else max(minimum, -bound)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(array) | (array > bound) | (array < low)
    if not bad.any():
        return None
    index = int(np.flatnonzero(bad)[0])
    reason = value_problem(float(array[index]), bound, unit, minimum=minimum)
    return index, reason or f"is {_show(float(array[index]))}, beyond ±{bound:g} {unit}".rstrip()

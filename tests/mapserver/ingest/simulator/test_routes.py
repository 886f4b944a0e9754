"""Routes: arc length, headings and the scenario shapes, checked against closed-form lengths."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapserver.ingest.simulator import routes


def _ramanujan(a: float, b: float) -> float:
    h = ((a - b) / (a + b)) ** 2
    return math.pi * (a + b) * (1 + 3 * h / (10 + math.sqrt(4 - 3 * h)))


@pytest.mark.parametrize(("a", "b"), [(14.0, 8.0), (3.0, 1.8), (5.0, 5.0)])
def test_ellipse_length_and_full_turn(a: float, b: float) -> None:
    route = routes.ellipse((1.0, -2.0), a, b, start_deg=0.0)
    assert route.length == pytest.approx(_ramanujan(a, b), rel=1e-4)
    assert route.theta[-1] - route.theta[0] == pytest.approx(2 * math.pi)
    assert np.allclose(route.position(0.0), (1.0 + a, -2.0))
    assert route.heading(0.0) == pytest.approx(math.pi / 2, abs=1e-3)  # counter-clockwise: north at the east end


@settings(max_examples=30, deadline=None)
@given(st.floats(4.0, 30.0), st.floats(4.0, 30.0), st.floats(0.5, 1.9))
def test_rounded_rectangle_length_closed_form(width: float, height: float, radius: float) -> None:
    route = routes.rounded_rectangle((0.0, 0.0), width, height, radius)
    expected = 2 * (width + height) - 8 * radius + 2 * math.pi * radius
    assert route.length == pytest.approx(expected, rel=1e-4)
    assert route.position(0.0) == pytest.approx((0.0, -height / 2))
    # heading is continuous across the lap seam and grows by 2π per lap
    assert route.heading(route.length + 0.3) - route.heading(0.3) == pytest.approx(2 * math.pi)


def test_positions_wrap_on_closed_routes_and_clip_on_open_ones() -> None:
    loop = routes.rounded_rectangle((0.0, 0.0), 10.0, 6.0, 2.0)
    assert np.allclose(loop.position(loop.length * 2 + 1.25), loop.position(1.25))
    line = routes.turtle((0.0, 0.0), 90.0, [("line", 5.0, 0)])
    assert np.allclose(line.position([-1.0, 2.0, 9.0]), [(0, 0), (0, 2), (0, 5)], atol=1e-9)
    assert np.allclose(line.normal(1.0), (-1.0, 0.0))  # left of north is west


def test_figure_eight_turns_both_ways() -> None:
    route = routes.figure_eight((0.0, 0.0), 14.0, 18.0)
    assert route.theta[-1] - route.theta[0] == pytest.approx(0.0, abs=1e-6)
    assert np.ptp(route.theta) > math.pi  # each lobe turns more than half a turn


def test_turtle_arcs_and_concat_join() -> None:
    bridge = routes.turtle((-14.0, -8.0), 0.0, [("arc", 8.0, 90.0), ("arc", 6.0, -180.0), ("arc", 8.0, 180.0)])
    assert np.allclose(bridge.xy[-1], (22.0, 0.0), atol=1e-9)
    assert bridge.length == pytest.approx(8 * math.pi / 2 + 6 * math.pi + 8 * math.pi, rel=1e-6)
    first = routes.segment(bridge, 0.0, 5.0)
    second = routes.segment(bridge, 5.0, bridge.length)
    joined = routes.concat([first, second])
    assert joined.length == pytest.approx(bridge.length, rel=1e-4)
    with pytest.raises(ValueError, match="do not join"):
        routes.concat([second, first])


def test_notched_loop_closes_and_mirrors() -> None:
    kw = {"side": 6.0, "height": 8.0, "corner": 3.0, "notch_depth": 3.0, "notch_radius": 1.5}
    ccw = routes.notched_loop((0.0, 0.0), 0.25, ccw=True, **kw)
    cw = routes.notched_loop((0.0, 0.0), 0.25, ccw=False, **kw)
    assert ccw.length == pytest.approx(cw.length)
    assert np.allclose(ccw.xy * (1, -1), cw.xy, atol=1e-9)  # mirror images across the stretch
    assert ccw.theta[-1] - ccw.theta[0] == pytest.approx(2 * math.pi)
    assert cw.theta[-1] - cw.theta[0] == pytest.approx(-2 * math.pi)
    with pytest.raises(ValueError, match="close"):
        routes.closed_turtle((0.0, 0.0), 0.0, [("line", 1.0, 0), ("arc", 1.0, 90.0)])

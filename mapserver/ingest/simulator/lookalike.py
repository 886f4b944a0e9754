"""Scenarios that try to break the merge safeguard: look-alike places with a strength that can be swept.

``twin`` / ``twin-overlap``. Two places 33 m or more apart that never see each other, each a loop
(:func:`~.routes.notched_loop`) dipping into an identical walled structure (the ``aliased`` scenario's
"H", :func:`~.scenarios._alias_structure`: the same walls with the same textures) that holds a straight
look-alike stretch ``lookalike_m`` metres long, driven eastwards in both places. Along the stretch the two
places look the same up to the per-visit noise, and the odometry of a straight drive agrees; outside the
structure the places differ (their own scattered walls and boxes, their own loop shapes). By default place 2
is driven clockwise: it enters the structure by the other legs, so only the straight stretch looks alike.
``lookalike_turns = 1`` drives place 2 counter-clockwise like place 1: both come down the same leg, turn
left onto the stretch and left again up the other leg, so the look-alike part holds two quarter turns
(180° of heading change) — the case the merge decision's turn rule cannot tell apart, where only the
probation can. ``session1``
maps place 1: it starts ``lead_m`` before its stretch and drives ``session1_laps`` of a lap, so its map
begins with the stretch. ``session2`` starts ``approach_m`` before a stretch and drives ``session2_laps``
laps: in ``twin`` it drives place 2 (every merge with session 1 is false); in ``twin-overlap`` it drives
place 1 like session 1, so after the stretch it keeps driving on session 1's ground (a merge is right,
and the stretch alone cannot tell the two scenarios apart). Both scenarios build the same world and the
same ``session1`` for a seed. ``twin-overlap`` also writes ``single``: one session driving session 1's
route and on for session 2's distance (the same ground, processed alone).

``symmetric`` / ``symmetric-overlap``. One counter-clockwise loop (a 30 m × 18 m rounded rectangle, corner
radius 5 m, centred at the origin) in a ground world made point-symmetric within two opposite sectors of
``symmetric_deg`` degrees about the loop centre (:func:`_symmetric_world`): the sector around the
north-east corner is copied, turned by 180°, onto the sector around the south-west corner. There the view
from pose (x, y, θ) equals the view from (−x, −y, θ + π): the opposite corner and side, seen in the opposite
direction of the world; driving the loop in the same sense as session 1, session 2 meets exactly those
poses, and its odometry agrees with the rotated track (a false alignment: 180° and twice the distance to
the centre off). Outside the sectors the world is its own. ``symmetric_deg = 180`` makes the whole world
symmetric; then no observation can tell the true alignment from the false one, so the overlap variant is
meaningful below 180 only. ``session1`` drives ``session1_laps`` (0.6) from ``session1_start`` (a fraction
of a lap from the middle of the bottom side, heading east), across the south-east and north-east corners.
``session2`` drives ``session2_laps`` (1.5) from ``session2_start``: in ``symmetric`` 0.7 lap, so it drives
the mirror sector (the west side and the south-west corner) before it reaches session 1's ground; in
``symmetric-overlap`` 0.1 lap, on session 1's ground. In ``symmetric`` a merge is right only when its
transform is the true one (session 2 reaches session 1's ground after about 0.3 lap). ``session2_reverse
= 1`` drives session 2 clockwise (its panoramic views then match session 1's only shifted by half a turn,
which the circle preset's template matching does not search). ``single`` drives session 1's start on for
both sessions' distance.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from mapserver.errors import InputError
from mapserver.ingest.simulator import routes
from mapserver.ingest.simulator.routes import Route
from mapserver.ingest.simulator.scenarios import (
    ALIAS_EXIT,
    ALIAS_LEG,
    ALIAS_TURN_RADIUS,
    GROUND_SPEED,
    Plan,
    ScenarioDef,
    SessionPlan,
    _alias_structure,
    _ground_plan,
    _ground_world,
    _laps_info,
    _session,
)
from mapserver.ingest.simulator.world import WorldBuilder

TWIN_SEPARATION_M = 20.0
"""Gap added between the two places' look-alike structures (beyond their own half spans)."""

TWIN_DEFAULTS = {
    "lookalike_m": 20.0,
    "lookalike_turns": 0.0,
    "lead_m": 2.0,
    "approach_m": 30.0,
    "session1_laps": 0.6,
    "session2_laps": 1.1,
}


def _twin_layout(
    seed: int, scale: float, params: dict[str, float]
) -> tuple[WorldBuilder, Route, Route, dict[str, Any]]:
    """Build the twin world: place 1 (west, counter-clockwise loop), place 2 (east, clockwise or, turns alike, ccw).

    Returns:
        The world builder, the routes of place 1 and place 2 (each starting at the middle of its stretch,
        heading east), and the ``lookalike`` info for scenario.json (centres of the stretches).

    """
    stretch = params["lookalike_m"]
    for key in ("lookalike_m", "lead_m", "approach_m"):
        if params[key] < 0:
            msg = f"{key} must be ≥ 0, got {params[key]!r}"
            raise InputError(msg)
    for key in ("session1_laps", "session2_laps"):
        if params[key] <= 0:
            msg = f"{key} must be > 0, got {params[key]!r}"
            raise InputError(msg)
    if params["lookalike_turns"] not in (0.0, 1.0):
        msg = f"lookalike_turns must be 0 or 1, got {params['lookalike_turns']!r}"
        raise InputError(msg)
    same_turns = params["lookalike_turns"] == 1.0
    half_span = (stretch / 2 + 2 * ALIAS_TURN_RADIUS + ALIAS_EXIT) * scale
    centre_1 = (-(half_span + TWIN_SEPARATION_M * scale), 0.0)
    centre_2 = (half_span + TWIN_SEPARATION_M * scale, 0.0)
    notch = {"corner": 3.0 * scale, "notch_depth": ALIAS_LEG * scale, "notch_radius": ALIAS_TURN_RADIUS * scale}
    place_1 = routes.notched_loop(centre_1, stretch, side=6.0 * scale, height=8.0 * scale, ccw=True, **notch)
    place_2 = routes.notched_loop(centre_2, stretch, side=5.0 * scale, height=11.0 * scale, ccw=same_turns,
                                  **notch)
    reach = half_span + 1.5 * scale
    discs = ((centre_1[0], centre_1[1], reach), (centre_2[0], centre_2[1], reach))
    builder = _ground_world(seed, [place_1, place_2], exclude=discs)
    walls = _alias_structure(builder, centre_1, stretch, scale)
    builder.copy_surfaces(walls, (centre_2[0] - centre_1[0], centre_2[1] - centre_1[1]))
    info = {"length_m": stretch, "centres": [list(centre_1), list(centre_2)]}
    return builder, place_1, place_2, info


def _twin_session(name: str, index: int, route: Route, before_m: float, laps: float, stretch: float) -> SessionPlan:
    """A session starting ``before_m`` before the stretch's west end, with the stretch's arc span in its info."""
    start = (-stretch / 2 - before_m) % route.length
    distance = laps * route.length
    info = {
        **_laps_info(route, distance, GROUND_SPEED),
        "start_m": round(start, 3),
        "lookalike_arc_m": [round(before_m, 3), round(before_m + stretch, 3)],
    }
    return _session(name, index, route, start, distance, info=info)


def _build_twin(name: str, seed: int, scale: float, params: dict[str, float], overlap: bool) -> Plan:
    builder, place_1, place_2, info = _twin_layout(seed, scale, params)
    stretch = info["length_m"]
    route_2 = place_1 if overlap else place_2
    s1 = _twin_session("session1", 1, place_1, params["lead_m"], params["session1_laps"], stretch)
    s2 = _twin_session("session2", 2, route_2, params["approach_m"], params["session2_laps"], stretch)
    single = None
    if overlap:
        distance = s1.spec.distance_m + s2.spec.distance_m
        single = _session("single", 0, place_1, s1.spec.start_m, distance,
                          info={**_laps_info(place_1, distance, GROUND_SPEED), "start_m": s1.spec.start_m})
    info = {
        "lookalike": {**info, "session2_place": 1 if overlap else 2, "true_overlap": overlap},
    }
    return _ground_plan(name, seed, params, [place_1, place_2], [s1, s2], single, scale, info, builder)


def build_twin(seed: int, scale: float, params: dict[str, float]) -> Plan:
    """Two places sharing a look-alike stretch; session 2 drives the other place (every merge is false)."""
    return _build_twin("twin", seed, scale, params, overlap=False)


def build_twin_overlap(seed: int, scale: float, params: dict[str, float]) -> Plan:
    """The twin world with both sessions in place 1: after the stretch session 2 drives session 1's ground."""
    return _build_twin("twin-overlap", seed, scale, params, overlap=True)


SYMMETRIC_DEFAULTS = {
    "symmetric_deg": 90.0,
    "session1_laps": 0.6,
    "session1_start": 0.0,
    "session2_start": 0.7,
    "session2_laps": 1.5,
    "session2_reverse": 0.0,
}
SYMMETRIC_OVERLAP_DEFAULTS = {**SYMMETRIC_DEFAULTS, "session2_start": 0.1}


def symmetric_sectors(
    points: npt.ArrayLike, centre: Sequence[float], axis: float, width: float
) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """Classify points by polar angle about ``centre``: in the source sector, in the mirror sector.

    The source sector is ``[axis − width/2, axis + width/2)`` (rad), the mirror sector the same turned by π;
    with ``width = π`` the two split the plane.
    """
    d = np.asarray(points, dtype=np.float64).reshape(-1, 2) - np.asarray(centre, dtype=np.float64)
    angle = np.arctan2(d[:, 1], d[:, 0]) - axis
    source = np.mod(angle + width / 2, 2 * math.pi) < width
    mirror = np.mod(angle + math.pi + width / 2, 2 * math.pi) < width
    return source, mirror & ~source


def _symmetric_world(seed: int, route: Route, width: float) -> WorldBuilder:
    """A ground world around ``route`` (centred at the origin) made point-symmetric within two sectors.

    The sectors are centred on the diagonal through the route's north-east corner: every surface whose
    midpoint lies in the south-west (mirror) sector is removed, and every surface in the north-east (source)
    sector is copied, rotated by 180° about the origin, into it.
    """
    builder = _ground_world(seed, [route])
    xy = route.xy
    axis = math.atan2(float(xy[:, 1].max()), float(xy[:, 0].max()))
    source, mirror = symmetric_sectors(builder.midpoints(), (0.0, 0.0), axis, width)
    builder.rotate_copy(np.flatnonzero(source).tolist(), (0.0, 0.0), math.pi)  # appended: indices stay valid
    builder.remove(np.flatnonzero(mirror).tolist())
    return builder


def _build_symmetric(name: str, seed: int, scale: float, params: dict[str, float]) -> Plan:
    width_deg = params["symmetric_deg"]
    if not 0.0 <= width_deg <= 180.0:
        msg = f"symmetric_deg must be within [0, 180], got {width_deg!r}"
        raise InputError(msg)
    for key in ("session1_laps", "session2_laps"):
        if params[key] <= 0:
            msg = f"{key} must be > 0, got {params[key]!r}"
            raise InputError(msg)
    route = routes.rounded_rectangle((0.0, 0.0), 30.0 * scale, 18.0 * scale, 5.0 * scale)
    builder = _symmetric_world(seed, route, math.radians(width_deg))
    length = route.length
    reverse = params["session2_reverse"] != 0.0
    route_2 = routes.from_points(route.xy[-2::-1], closed=True) if reverse else route
    start_1 = (params["session1_start"] % 1.0) * length
    start_2 = (params["session2_start"] % 1.0) * length
    d1, d2 = params["session1_laps"] * length, params["session2_laps"] * length
    sessions = [
        _session("session1", 1, route, start_1, d1,
                 info={**_laps_info(route, d1, GROUND_SPEED), "start_m": round(start_1, 3)}),
        _session("session2", 2, route_2, (length - start_2) % length if reverse else start_2, d2,
                 info={**_laps_info(route, d2, GROUND_SPEED), "start_m": round(start_2, 3), "reverse": reverse}),
    ]
    single = _session("single", 0, route, start_1, d1 + d2,
                      info={**_laps_info(route, d1 + d2, GROUND_SPEED), "start_m": round(start_1, 3)})
    xy = route.xy
    info = {"symmetric": {
        "centre": [0.0, 0.0],
        "axis_deg": round(math.degrees(math.atan2(float(xy[:, 1].max()), float(xy[:, 0].max()))), 3),
        "sector_deg": width_deg,
    }}
    return _ground_plan(name, seed, params, [route], sessions, single, scale, info, builder)


def build_symmetric(seed: int, scale: float, params: dict[str, float]) -> Plan:
    """A point-symmetric loop; session 2 meets the mirror of session 1's ground before its true ground."""
    return _build_symmetric("symmetric", seed, scale, params)


def build_symmetric_overlap(seed: int, scale: float, params: dict[str, float]) -> Plan:
    """The symmetric loop; session 2 starts on session 1's ground (a merge is right)."""
    return _build_symmetric("symmetric-overlap", seed, scale, params)


DEFINITIONS: tuple[ScenarioDef, ...] = (
    ScenarioDef("twin", "two places sharing a look-alike stretch; session 2 in the other place (never merge)",
                TWIN_DEFAULTS, build_twin),
    ScenarioDef("twin-overlap", "the twin world, both sessions in place 1 (a merge is right)",
                TWIN_DEFAULTS, build_twin_overlap),
    ScenarioDef("symmetric", "a loop point-symmetric in two opposite sectors; session 2 meets the mirror first",
                SYMMETRIC_DEFAULTS, build_symmetric),
    ScenarioDef("symmetric-overlap", "the symmetric loop; session 2 starts on session 1's ground (a merge is right)",
                SYMMETRIC_OVERLAP_DEFAULTS, build_symmetric_overlap),
)

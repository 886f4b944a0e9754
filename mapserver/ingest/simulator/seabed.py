"""``seabed``: an AUV's lawnmower survey over a rocky seabed, then a revisit of its first leg (4-DoF).

The vehicle flies ``legs`` (even) parallel legs of ``leg_m`` metres, ``spacing_m`` apart (turning on half circles
at the ends), then turns back to the start and flies the first leg again: the revisit. Its depth follows the
seabed (the same depth at the same place on both visits): ``z = −2 − 0.5·sin(π·x/leg_m) − 0.1·y`` (metres,
up; ``x`` along the legs, ``y`` across). Rocks (textured boxes) are scattered over the area and rock walls
line it, seen by the 360° camera of ``cave3d`` through the same water (fog 4 m).

It carries the AUV navigation sensors by default (``nav=1``: DVL, IMU, pressure, ``/tf_static``;
:mod:`.navsensors`) and no wheel-style odometry (``odometry=0``; ``odometry=1`` adds the drifting
``nav_msgs/Odometry`` of :mod:`.drive`). ``single`` is the whole mission; ``session1`` the survey;
``session2`` the revisit (from the end of the last leg).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mapserver.errors import InputError
from mapserver.ingest.simulator import routes
from mapserver.ingest.simulator.navsensors import NavSensors
from mapserver.ingest.simulator.routes import Route
from mapserver.ingest.simulator.scenarios import (
    CAVE_CAMERA,
    CAVE_NOISE,
    CAVE_RATES,
    CAVE_SPEED,
    FloatArray,
    Plan,
    ScenarioDef,
    _laps_info,
    _session,
    check_switches,
)
from mapserver.ingest.simulator.world import WorldBuilder


def lawnmower(legs: int, leg_m: float, spacing_m: float) -> tuple[Route, float]:
    """Return the survey-then-revisit route and the arc length where the revisit begins."""
    radius = spacing_m / 2.0
    moves: list[tuple[str, float, float]] = []
    for k in range(legs):
        moves.append(("line", leg_m, 0.0))
        if k < legs - 1:
            moves.append(("arc", radius, 180.0 if k % 2 == 0 else -180.0))
    survey = routes.turtle((0.0, 0.0), 0.0, moves)
    # back to the start (an even number of legs ends heading −x at the start's side): turn left onto −y,
    # fly down to the first leg's line, turn left onto it (heading +x)
    across = (legs - 1) * spacing_m - 2.0 * radius
    back = [("arc", radius, 90.0), ("line", max(across, 0.01), 0.0), ("arc", radius, 90.0)]
    end = survey.position(np.asarray([survey.length]))[0]
    tail = routes.turtle((float(end[0]), float(end[1])), 180.0, [*back, ("line", leg_m, 0.0)])
    return routes.concat([survey, tail]), survey.length


def build_seabed(seed: int, scale: float, params: dict[str, float]) -> Plan:
    """The lawnmower survey and its revisit (module docstring)."""
    check_switches(params, ("nav", "odometry"))
    legs = int(params["legs"])
    whole = legs == params["legs"] and legs % 2 == 0 and 2 <= legs <= 12
    if not (whole and params["leg_m"] > 0 and params["spacing_m"] > 0):
        msg = "seabed needs an even number of legs, 2 to 12, and positive leg_m and spacing_m"
        raise InputError(msg)
    leg, spacing = params["leg_m"] * scale, params["spacing_m"] * scale
    route, revisit_m = lawnmower(legs, leg, spacing)

    def depth(s: FloatArray) -> FloatArray:
        xy = route.position(np.asarray(s, dtype=np.float64))
        return -2.0 - 0.5 * np.sin(math.pi * xy[:, 0] / leg) - 0.1 * xy[:, 1]

    rng = np.random.default_rng([seed, 0])
    builder = WorldBuilder(seed, texels_per_m=40.0, feature_m=0.15, floor_z=-5.0, ceiling_z=0.0,
                           floor_albedo=0.35, ceiling_albedo=0.7)  # fmt: skip
    keep = route.points(0.05)
    lo, hi = keep.min(axis=0) - 2.0, keep.max(axis=0) + 2.0
    builder.scatter_boxes(rng, keep, (lo[0], lo[1], hi[0], hi[1]), density=1.5, clearance=0.5,
                          size=(0.1, 0.4), height=(0.5, 4.0))  # fmt: skip
    builder.add_polyline([(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])], top=0.0, closed=True)
    world = builder.build()
    total = route.length
    info: dict[str, Any] = {"revisit_start_m": round(revisit_m, 3), "route_length_m": round(total, 3)}
    sessions = [
        _session("session1", 1, route, 0.0, revisit_m, speed=CAVE_SPEED, depth=depth,
                 info=_laps_info(route, revisit_m, CAVE_SPEED)),
        _session("session2", 2, route, revisit_m, total - revisit_m - 1e-6, speed=CAVE_SPEED, depth=depth,
                 info={**_laps_info(route, total - revisit_m, CAVE_SPEED), "start_m": round(revisit_m, 3)}),
    ]  # fmt: skip
    single = _session("single", 0, route, 0.0, total - 1e-6, speed=CAVE_SPEED, depth=depth,
                      info=_laps_info(route, total, CAVE_SPEED))  # fmt: skip
    return Plan(
        scenario="seabed", preset="poseidon-lvc", world=world, camera=CAVE_CAMERA, rates=CAVE_RATES,
        noise=CAVE_NOISE.scaled(min(scale, 1.0)), sessions=tuple(sessions), single=single, params=params,
        info=info, navigation=NavSensors() if params["nav"] == 1.0 else None, odometry=params["odometry"] == 1.0,
    )  # fmt: skip


DEFINITIONS: tuple[ScenarioDef, ...] = (
    ScenarioDef("seabed", "AUV lawnmower survey over a rocky seabed, then a revisit of the first leg (4-DoF, "
                "DVL + IMU + pressure)", {"legs": 4.0, "leg_m": 6.0, "spacing_m": 1.5, "nav": 1.0, "odometry": 0.0},
                build_seabed),
)  # fmt: skip

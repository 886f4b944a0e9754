"""The ``building`` and ``terrain`` scenarios: routes that change height, for the 4-DoF ``neuroslam`` preset.

``building``: two storeys of one floor plan joined by a spiral ramp. On each storey a corridor loop (a
``width_m`` × ``depth_m`` rounded rectangle, corner radius 3 m, driven counter-clockwise from the middle of its
south side, the *landing*) is lined on both sides, 1.5 m from the route, with full-height wall panels and
doorways between them; furniture (boxes) stands in the rooms behind. Storey 2 is storey 1 copied ``storey_m``
higher, the same walls and boxes, with a share ``restyle`` of its surfaces given textures of their own: the two
storeys look alike but not the same. South of the landing a stairwell (a cylinder wall with a central column,
both two storeys tall and textured over their whole height) holds a ramp that turns once, clockwise, at
radius ``ramp_radius_m`` while it climbs one storey, and comes back to the landing one storey up. The world
has a local floor and a storey (:class:`~.world.World`): the camera sees its own storey, and on the ramp the
band between floor and ceiling at its height.

Sessions: ``single`` drives ``laps`` laps of storey 1, the ramp, and ``laps`` laps of storey 2 (revisits on
each floor, one ramp); ``floor1`` and ``floor2`` drive ``laps`` laps of one storey each; ``stairs`` comes along
the second half of storey 1's loop to the landing, takes the ramp and drives the first half of storey 2's
loop. ``floors`` in scenario.json gives the storeys' heights and the ramp's arc lengths in each session.

``terrain``: ``laps`` laps of a 30 m × 20 m rounded rectangle over hills (a sum of ``hills`` Gaussian bumps,
up to ``hill_m`` high and 4–8 m wide, drawn per seed); the vehicle follows the ground, free-standing walls and
boxes stand on it. The world has a local floor (the camera sees flat ground at its own height).

Both scenarios equip the vehicle as NeuroSLAM's SynPerData (a forward camera of ``fov_deg``, 81.5° by
default, 4:3 square pixels, written raw) driving ``speed`` m/s with ``camera_hz`` frames and 10 Hz
odometry whose vertical speed has a bias and white noise (the odometry's ``dz`` drifts, as the cave's).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from mapserver.errors import InputError
from mapserver.ingest.simulator import routes
from mapserver.ingest.simulator.drive import Noise, Rates
from mapserver.ingest.simulator.render import Camera
from mapserver.ingest.simulator.routes import Route
from mapserver.ingest.simulator.scenarios import Plan, ScenarioDef, SessionPlan, _ground_world, _session
from mapserver.ingest.simulator.world import WorldBuilder

FloatArray = npt.NDArray[np.float64]

CORNER_M = 3.0
CORRIDOR_HALF_M = 1.5
"""Distance of the corridor walls from the route."""
STAIRWELL_WALL_M = 1.3
"""Distance of the stairwell's cylinder wall and column from the ramp."""
LEVEL_NOISE = Noise(
    lateral_m=0.1,
    speed_variation=0.08,
    scale_error=0.025,
    yaw_bias=0.004,
    vz_bias=0.003,
    vz_noise=0.01,
    session_scale_error=0.003,
    session_yaw_bias=0.0005,
    session_yaw_walk=2e-5,
)
"""A wheeled robot with a barometric or visual-inertial height rate: the ground scenarios' odometry errors
plus a 0.003 m/s vertical-speed bias and 0.01 m/s of vertical-speed noise per message."""


def _camera(params: dict[str, float]) -> Camera:
    """The forward camera: ``fov_deg`` over 128 × 96 square pixels, 1.2 m up, seeing 12 m."""
    return Camera(
        width=128,
        height=96,
        hfov_deg=params["fov_deg"],
        vfov_deg=None,
        mount_height=1.2,
        fog_length=20.0,
        max_range=12.0,
        fade=2.0,
        fog_level=0.6,
        blur_px=0.7,
        vblur_px=0.7,
    )


def _level_plan(
    name: str,
    builder: WorldBuilder,
    params: dict[str, float],
    scale: float,
    sessions: list[SessionPlan],
    single: SessionPlan,
    info: dict[str, Any],
) -> Plan:
    """The plan of a scenario that changes height: forward camera, rates and noise of the module docstring."""
    if not (params["speed"] > 0 and params["camera_hz"] > 0 and 0 < params["fov_deg"] < 180):
        msg = f"speed and camera_hz must be positive and 0 < fov_deg < 180, got {params!r}"
        raise InputError(msg)
    return Plan(
        scenario=name, preset="neuroslam", world=builder.build(), camera=_camera(params),
        rates=Rates(camera_hz=params["camera_hz"], odom_hz=10.0, camera_offset_s=0.031),
        noise=LEVEL_NOISE.scaled(min(scale, 1.0)), sessions=tuple(sessions), single=single, params=params, info=info,
    )  # fmt: skip


def _profile(knots: list[tuple[float, float]]) -> Callable[[FloatArray], FloatArray]:
    """Return z(s), piecewise linear through the (arc length, height) knots, constant beyond them."""
    s_k = np.array([k[0] for k in knots])
    z_k = np.array([k[1] for k in knots])

    def height(s: FloatArray) -> FloatArray:
        return np.interp(np.asarray(s, dtype=np.float64), s_k, z_k)

    return height


# ----------------------------------------------------------------------------------------------- building


def _storey(
    builder: WorldBuilder,
    rng: np.random.Generator,
    loop: Route,
    keep: FloatArray,
    stairwell: tuple[float, float, float],
    storey: float,
) -> list[int]:
    """Build storey 1: corridor panels along the loop, furniture in the rooms, the outer wall; return its surfaces."""
    first = len(builder.surfaces)
    builder.line_route(rng, loop.xy[:-1], keep, offset=CORRIDOR_HALF_M, clearance=1.2, panel=(1.0, 3.0),
                       gap=(0.4, 1.2), height=(storey, storey))  # fmt: skip
    lo = keep.min(axis=0) - 5.0
    hi = keep.max(axis=0) + 5.0
    builder.scatter_boxes(rng, keep, (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])), density=0.2,
                          clearance=CORRIDOR_HALF_M + 0.3, size=(0.3, 1.0), height=(0.6, 2.4),
                          exclude=(stairwell,))  # fmt: skip
    builder.add_polyline([(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])], top=storey, closed=True)
    return list(range(first, len(builder.surfaces)))


def _stairwell(
    builder: WorldBuilder, centre: tuple[float, float], radius: float, landing_y: float, storey: float
) -> None:
    """Add the stairwell's cylinder wall (open towards the corridor) and central column, two storeys tall."""
    angles = np.linspace(0.0, 2.0 * math.pi, 25)
    outer = radius + STAIRWELL_WALL_M
    ring = [(centre[0] + outer * math.cos(a), centre[1] + outer * math.sin(a)) for a in angles]
    for p, q in itertools.pairwise(ring):
        if max(p[1], q[1]) < landing_y - CORRIDOR_HALF_M:  # the corridor side stays open
            builder.add_wall(p, q, top=2.0 * storey, style="stripes")
    inner = radius - STAIRWELL_WALL_M
    column = [(centre[0] + inner * math.cos(a), centre[1] + inner * math.sin(a)) for a in angles[:-1]]
    builder.add_polyline(column, top=2.0 * storey, closed=True, style="bricks")


def _restyle(builder: WorldBuilder, rng: np.random.Generator, surfaces: list[int], share: float) -> list[int]:
    """Give a random ``share`` of ``surfaces`` textures of their own; return those surfaces."""
    chosen = sorted(int(k) for k in rng.choice(surfaces, size=round(share * len(surfaces)), replace=False))
    for k in chosen:
        builder.retexture(k)
    return chosen


def build_building(seed: int, scale: float, params: dict[str, float]) -> Plan:
    """Build the ``building`` plan (module docstring)."""
    storey, share, laps = params["storey_m"], params["restyle"], params["laps"]
    width, depth, radius = params["width_m"] * scale, params["depth_m"] * scale, params["ramp_radius_m"] * scale
    if not (storey >= 2.0 and 0.0 <= share <= 1.0 and laps >= 1 and laps == int(laps)):
        msg = f"storey_m must be ≥ 2, restyle in [0, 1] and laps a whole number ≥ 1, got {params!r}"
        raise InputError(msg)
    if min(width, depth) <= 2 * CORNER_M * scale + 1.0 or radius < STAIRWELL_WALL_M + 0.5:
        msg = f"the floor must be wider than its corners and the ramp radius ≥ {STAIRWELL_WALL_M + 0.5} m: {params!r}"
        raise InputError(msg)
    loop = routes.rounded_rectangle((0.0, 0.0), width, depth, CORNER_M * scale, start="bottom")
    landing = (0.0, -depth / 2)
    ramp = routes.turtle(landing, 0.0, [("arc", radius, -360.0)])
    centre = (landing[0], landing[1] - radius)
    length = loop.length
    rng = np.random.default_rng([seed, 0])
    builder = WorldBuilder(seed, texels_per_m=10.0, feature_m=0.5, floor_albedo=0.3, ceiling_albedo=0.7,
                           local_floor=True, storey=storey)  # fmt: skip
    keep = np.vstack([loop.points(0.25), ramp.points(0.25)])
    floor1 = _storey(builder, rng, loop, keep, (*centre, radius + STAIRWELL_WALL_M + 0.5), storey)
    floor2 = builder.copy_surfaces(floor1, (0.0, 0.0), rise=storey)
    restyled = _restyle(builder, np.random.default_rng([seed, 5]), floor2, share)
    _stairwell(builder, centre, radius, landing[1], storey)
    sessions = _building_sessions(loop, ramp, laps, storey, params["speed"])
    info = {
        "floors": {
            "z_m": [0.0, storey],
            "storey_m": storey,
            "landing": list(landing),
            "ramp_centre": list(centre),
            "ramp_radius_m": radius,
            "restyled": len(restyled),
            "surfaces_per_floor": len(floor1),
            "lap_length_m": round(length, 3),
            "ramp_arc_m": {s.name: s.info["ramp_arc_m"] for s in sessions if "ramp_arc_m" in s.info},
        }
    }
    single = next(s for s in sessions if s.name == "single")
    return _level_plan("building", builder, params, scale, sessions, single, info)


def _building_sessions(loop: Route, ramp: Route, laps: float, storey: float, speed: float) -> list[SessionPlan]:
    """The building's sessions (module docstring): single, floor1, floor2, stairs."""
    length, up = loop.length, ramp.length
    whole = routes.segment(loop, 0.0, laps * length)
    single_route = routes.concat([whole, ramp, whole])
    a = laps * length
    half = length / 2
    stairs_route = routes.concat([routes.segment(loop, half, length), ramp, routes.segment(loop, 0.0, half)])
    flat = _profile([(0.0, 0.0)])
    high = _profile([(0.0, storey)])
    plans = [
        ("single", single_route, _profile([(a, 0.0), (a + up, storey)]), [a, a + up]),
        ("floor1", whole, flat, None),
        ("floor2", whole, high, None),
        ("stairs", stairs_route, _profile([(half, 0.0), (half + up, storey)]), [half, half + up]),
    ]
    out = []
    for index, (name, route, height, arc) in enumerate(plans):
        info: dict[str, Any] = {"length_m": round(route.length, 3)}
        if arc is not None:
            info["ramp_arc_m"] = [round(arc[0], 3), round(arc[1], 3)]
        out.append(_session(name, index, route, 0.0, route.length, speed=speed, depth=height, info=info))
    return out


# ------------------------------------------------------------------------------------------------ terrain


def _hills(
    seed: int, count: int, height: float, bounds: tuple[float, float, float, float]
) -> Callable[[FloatArray], FloatArray]:
    """Return h(xy) for (…, 2) points: ``count`` Gaussian bumps up to ``height`` m, 4–8 m wide, inside bounds."""
    rng = np.random.default_rng([seed, 7])
    x0, y0, x1, y1 = bounds
    centres = np.column_stack([rng.uniform(x0, x1, count), rng.uniform(y0, y1, count)])
    peaks = height * rng.uniform(0.4, 1.0, count)
    widths = rng.uniform(4.0, 8.0, count)

    def ground(xy: FloatArray) -> FloatArray:
        p = np.asarray(xy, dtype=np.float64)
        d2 = np.sum((p[..., None, :] - centres) ** 2, axis=-1)
        return np.asarray(np.exp(-d2 / (2.0 * widths**2)) @ peaks, dtype=np.float64)

    return ground


def build_terrain(seed: int, scale: float, params: dict[str, float]) -> Plan:
    """Build the ``terrain`` plan (module docstring)."""
    if not (params["hill_m"] >= 0.0 and params["hills"] >= 0 and params["laps"] > 0):
        msg = f"hill_m and hills must be ≥ 0 and laps > 0, got {params!r}"
        raise InputError(msg)
    route = routes.rounded_rectangle((0.0, 0.0), 30.0 * scale, 20.0 * scale, 5.0 * scale)
    ground = _hills(
        seed, int(params["hills"]), params["hill_m"], (-15.0 * scale, -10.0 * scale, 15.0 * scale, 10.0 * scale)
    )

    def height(s: FloatArray) -> FloatArray:
        return ground(route.position(s))

    builder = _ground_world(seed, [route])
    builder.local_floor = True
    midpoints = builder.midpoints()
    builder.raise_surfaces(range(len(builder.surfaces)), (ground(midpoints) - 0.3).tolist())
    distance = params["laps"] * route.length
    single = _session(
        "single",
        0,
        route,
        0.0,
        distance,
        speed=params["speed"],
        depth=height,
        info={"laps": params["laps"], "lap_length_m": round(route.length, 3)},
    )
    z = height(np.linspace(0.0, route.length, 400))
    info = {"terrain": {"route_z_m": [round(float(z.min()), 3), round(float(z.max()), 3)]}}
    return _level_plan("terrain", builder, params, scale, [single], single, info)


_CAMERA = {"fov_deg": 81.5, "camera_hz": 2.0, "speed": 1.0}

DEFINITIONS: tuple[ScenarioDef, ...] = (
    ScenarioDef(
        "building",
        "two look-alike storeys joined by a spiral ramp; laps of each, forward camera (4-DoF, neuroslam)",
        {
            "laps": 2.0,
            "storey_m": 3.0,
            "restyle": 0.3,
            "width_m": 16.0,
            "depth_m": 10.0,
            "ramp_radius_m": 2.5,
            **_CAMERA,
        },
        build_building,
    ),
    ScenarioDef(
        "terrain",
        "laps of a loop over hills, forward camera (4-DoF, neuroslam)",
        {"laps": 2.0, "hills": 5.0, "hill_m": 2.5, **_CAMERA},
        build_terrain,
    ),
)

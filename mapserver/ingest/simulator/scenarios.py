"""The simulator's scenarios: world, routes and sessions of each named mission.

Ground scenarios (``loop``, ``figure8``, ``ellipse``, ``bridge``, ``chain5``, ``aliased``) share one world
design and suit the ``circle`` preset (Menezes et al. 2023, Virtual Tour: 256×64 panoramic images,
1 m pose cells): every route is lined on both sides, 2.5 m away, with façade panels of random length,
height and texture separated by gaps, and textured boxes are scattered farther off the routes. A
panoramic camera 1 m above the ground sees 6 m far (fog beyond). The vehicle drives at 0.5 m/s with
1 Hz images (0.5 m between frames) and 10 Hz odometry and ground truth.

``cave3d`` is an underwater cave for the 4-DoF ``poseidon`` preset (0.1 m pose cells): a rock-walled
passage around an elliptic loop at 0.15 m/s with 2 Hz images, the vehicle's depth changing along the
loop; walls reach from the floor to the water surface and are banded in depth, so the camera's depth
changes what it sees. ``--param sonar=1`` adds a forward-looking imaging sonar (``/robot/sonar/image``,
:class:`~.render.Sonar`: 64 beams over 130°, 48 range bins to 5 m, at the camera's rate and stamps), the
second modality of the ``sdr-htm`` front-end; ``--param turbidity=T`` shortens the camera's fog length
to 4 m / (1 + T) (sound does not fade with it).

The look-alike scenarios that try to break the merge safeguard (``twin``, ``twin-overlap``, ``symmetric``,
``symmetric-overlap``) are ground scenarios too; they live in :mod:`.lookalike`.

Every scenario takes ``scale`` (route and world size; noise lengths scale with it, frame spacing does not)
and its own parameters (:data:`SCENARIOS` lists them with their defaults).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from mapserver.errors import InputError
from mapserver.ingest.simulator import routes
from mapserver.ingest.simulator.drive import DriveSpec, Noise, Rates
from mapserver.ingest.simulator.navsensors import NavSensors
from mapserver.ingest.simulator.render import Camera, Lighting, Sonar
from mapserver.ingest.simulator.routes import Route
from mapserver.ingest.simulator.world import World, WorldBuilder
from mapserver.ingest.writer import ImageEncoding

FloatArray = npt.NDArray[np.float64]

DAY_NS = 86_400 * 1_000_000_000
T0_NS = 1_700_000_000 * 1_000_000_000
"""Stamp of the first session's first odometry message; session k starts k days later."""

GROUND_SPEED = 0.5
GROUND_RATES = Rates(camera_hz=1.0, odom_hz=10.0, camera_offset_s=0.037)
GROUND_CAMERA = Camera(
    width=256, height=64, hfov_deg=360.0, vfov_deg=30.0, mount_height=1.5, fog_length=25.0, max_range=12.0,
    fade=2.0, fog_level=0.6, blur_px=7.0, vblur_px=0.7,
)
GROUND_NOISE = Noise(session_scale_error=0.003, session_yaw_bias=0.0005, session_yaw_walk=2e-5)
"""A wheeled robot: the vehicle's ±2.5 % scale error and ±0.004 rad/s yaw-rate bias are shared by all its
sessions; each session adds a 0.3 % scale change, a 0.0005 rad/s turn-on bias offset and a 2e-5 rad/s/√s
bias random walk (drive module docstring)."""
CLEARANCE = 2.0
WALL_DENSITY = 0.5
WALL_LENGTH = (1.0, 4.0)
WALL_HEIGHT = (0.8, 3.5)
BOX_DENSITY = 0.1
TEXTURE_FEATURE_M = 1.2
MARGIN = 6.0

CAVE_SPEED = 0.15
CAVE_RATES = Rates(camera_hz=2.0, odom_hz=10.0, camera_offset_s=0.023)
CAVE_CAMERA = Camera(
    width=256, height=96, hfov_deg=360.0, vfov_deg=50.0, mount_height=0.0, fog_length=4.0, max_range=3.5,
    fade=0.3, fog_level=0.25, blur_px=4.0, vblur_px=0.7,
)
CAVE_NOISE = Noise(
    lateral_m=0.03, speed_variation=0.08, depth_m=0.02, scale_error=0.03, yaw_bias=0.006, vz_bias=0.004,
    speed_noise=0.01, yaw_noise=0.02, vz_noise=0.005, gain=0.04, pixel_noise=2.0,
    session_scale_error=0.003, session_yaw_bias=0.0005, session_yaw_walk=2e-5,
)
"""An underwater vehicle: DVL scale error, gyro yaw-rate bias and vertical-speed bias of the vehicle, the same
per-session effects as on the ground."""


@dataclass(frozen=True)
class SessionPlan:
    """One log to write.

    Attributes:
        name: session name (``single`` for the single-session log).
        spec: what the vehicle drives.
        t0_ns: stamp of the first odometry message.
        info: extra JSON for scenario.json (e.g. lap boundaries).

    """

    name: str
    spec: DriveSpec
    t0_ns: int
    info: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Plan:
    """A scenario ready to simulate.

    Attributes:
        scenario: scenario name.
        preset: the engine preset that suits its logs.
        world: the scene.
        camera: camera model.
        rates: message rates.
        noise: variation and sensor noise.
        sessions: the multisession logs.
        single: the single-session log, or None.
        params: the effective scenario parameters.
        info: extra JSON for scenario.json.
        sonar: the forward-looking sonar, or None.
        sonar_topic: its topic.
        image_encoding: how camera frames are written (``mono8``, or ``jpeg`` compressed frames).
        jpeg_quality: JPEG quality of ``jpeg`` frames.
        lighting: how the light changes during a session, or None for a steady light.
        navigation: the AUV navigation sensors (DVL, IMU, pressure, ``/tf_static``) written besides, or None.
        odometry: whether the ``nav_msgs/Odometry`` topic is written.

    """

    scenario: str
    preset: str
    world: World
    camera: Camera
    rates: Rates
    noise: Noise
    sessions: tuple[SessionPlan, ...]
    single: SessionPlan | None
    params: dict[str, float]
    info: dict[str, Any] = field(default_factory=dict)
    sonar: Sonar | None = None
    sonar_topic: str = "/robot/sonar/image"
    image_encoding: ImageEncoding = "mono8"
    jpeg_quality: int = 95
    lighting: Lighting | None = None
    navigation: NavSensors | None = None
    odometry: bool = True


@dataclass(frozen=True)
class ScenarioDef:
    """A named scenario: description, parameters with defaults, and its builder."""

    name: str
    description: str
    defaults: Mapping[str, float]
    build: Callable[[int, float, dict[str, float]], Plan]


# ------------------------------------------------------------------------------------------------- worlds


def _ground_world(
    seed: int,
    route_list: list[Route],
    *,
    exclude: tuple[tuple[float, float, float], ...] = (),
    extra_bounds: tuple[tuple[float, float, float], ...] = (),
) -> WorldBuilder:
    """Free-standing walls and boxes scattered off every route, and a boundary wall around everything."""
    rng = np.random.default_rng([seed, 0])
    builder = WorldBuilder(seed, texels_per_m=10.0, feature_m=TEXTURE_FEATURE_M, floor_albedo=0.3)
    keep = np.vstack([r.points(0.25) for r in route_list])
    lo = keep.min(axis=0) - MARGIN
    hi = keep.max(axis=0) + MARGIN
    for x, y, r in extra_bounds:  # discs that must lie inside the boundary wall
        lo = np.minimum(lo, (x - r - 1.0, y - r - 1.0))
        hi = np.maximum(hi, (x + r + 1.0, y + r + 1.0))
    bounds = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
    builder.scatter_walls(
        rng, keep, bounds, density=WALL_DENSITY, clearance=CLEARANCE, length=WALL_LENGTH, height=WALL_HEIGHT,
        exclude=exclude,
    )
    builder.scatter_boxes(
        rng, keep, bounds, density=BOX_DENSITY, clearance=CLEARANCE, height=WALL_HEIGHT, exclude=exclude
    )
    builder.add_polyline(
        [(lo[0] - 1, lo[1] - 1), (hi[0] + 1, lo[1] - 1), (hi[0] + 1, hi[1] + 1), (lo[0] - 1, hi[1] + 1)],
        top=5.0,
        closed=True,
    )
    return builder


def _session(name: str, index: int, route: Route, start_m: float, distance_m: float, **kw: Any) -> SessionPlan:
    speed = kw.pop("speed", GROUND_SPEED)
    info = kw.pop("info", {})
    spec = DriveSpec(route=route, start_m=start_m, distance_m=distance_m, speed=speed, **kw)
    return SessionPlan(name=name, spec=spec, t0_ns=T0_NS + index * DAY_NS, info=info)


def _laps_info(route: Route, distance_m: float, speed: float, turn_s: float = 0.0) -> dict[str, Any]:
    """Nominal lap boundaries (s after the session start; the speed variation shifts them slightly)."""
    laps = distance_m / route.length
    return {
        "laps": round(laps, 3),
        "lap_length_m": round(route.length, 3),
        "nominal_lap_s": [round(turn_s + k * route.length / speed, 3) for k in range(1, int(laps) + 1)],
    }


def _ground_plan(
    name: str, seed: int, params: dict[str, float], route_list: list[Route], sessions: list[SessionPlan],
    single: SessionPlan | None, scale: float, info: dict[str, Any] | None = None,
    builder: WorldBuilder | None = None,
) -> Plan:
    world = (builder or _ground_world(seed, route_list)).build()
    return Plan(
        scenario=name,
        preset="circle",
        world=world,
        camera=GROUND_CAMERA,
        rates=GROUND_RATES,
        noise=GROUND_NOISE.scaled(min(scale, 1.0)),
        sessions=tuple(sessions),
        single=single,
        params=params,
        info=info or {},
    )


# ---------------------------------------------------------------------------------------------- scenarios


def build_loop(seed: int, scale: float, params: dict[str, float]) -> Plan:
    """One session, ``laps`` laps of a 24 m × 14 m rounded rectangle (corner radius 4 m)."""
    route = routes.rounded_rectangle((0.0, 0.0), 24.0 * scale, 14.0 * scale, 4.0 * scale)
    distance = params["laps"] * route.length
    single = _session("single", 0, route, 0.0, distance, info=_laps_info(route, distance, GROUND_SPEED))
    return _ground_plan("loop", seed, params, [route], [single], single, scale)


def build_figure8(seed: int, scale: float, params: dict[str, float]) -> Plan:
    """One session, ``laps`` laps of a figure-eight (lemniscate of Gerono, 28 m × 18 m)."""
    route = routes.figure_eight((0.0, 0.0), 14.0 * scale, 18.0 * scale)
    distance = params["laps"] * route.length
    single = _session("single", 0, route, 0.0, distance, info=_laps_info(route, distance, GROUND_SPEED))
    return _ground_plan("figure8", seed, params, [route], [single], single, scale)


def build_ellipse(seed: int, scale: float, params: dict[str, float]) -> Plan:
    """Menezes et al.'s Virtual Tour: an ellipse (semi-axes 14 m × 8 m), counter-clockwise.

    ``single``: ``single_laps`` laps from the start point (the right end of the ellipse). Multisession split:
    ``session1`` covers the first ``session1_laps`` (3/4) of a lap from the same start; ``session2``
    starts in the middle of the unmapped rest (at ``session2_start`` of a lap, default 7/8) and runs
    ``session2_laps`` laps, reaching session 1's start after about 1/8 lap. ``heading_offset_deg`` makes
    session 2 begin with an in-place turn of that angle (its start heading, and so its map frame, differ
    by that angle from the default variant).
    """
    route = routes.ellipse((0.0, 0.0), 14.0 * scale, 8.0 * scale, start_deg=0.0)
    length = route.length
    d_single = params["single_laps"] * length
    d1 = params["session1_laps"] * length
    s2 = params["session2_start"] * length
    d2 = params["session2_laps"] * length
    turn = params["heading_offset_deg"]
    turn_s = abs(math.radians(turn)) / 0.3
    sessions = [
        _session("session1", 1, route, 0.0, d1, info=_laps_info(route, d1, GROUND_SPEED)),
        _session(
            "session2", 2, route, s2, d2, turn_deg=turn,
            info={**_laps_info(route, d2, GROUND_SPEED, turn_s), "start_m": round(s2, 3), "turn_deg": turn},
        ),
    ]
    single = _session("single", 0, route, 0.0, d_single, info=_laps_info(route, d_single, GROUND_SPEED))
    return _ground_plan("ellipse", seed, params, [route], sessions, single, scale)


def build_bridge(seed: int, scale: float, params: dict[str, float]) -> Plan:
    """Two circular loops (radius 8 m, 28 m apart) mapped by one session each, and a bridging session.

    ``session1`` and ``session2`` drive ``laps`` laps of the west and east loop from their south points.
    ``session3`` starts at the west loop's south point, follows it for a quarter lap (12.6 m), crosses on
    a 6 m-radius semicircle to the east loop's west point and follows it for half a lap (25.1 m), so it
    overlaps both earlier sessions in the same direction of travel.
    """
    r, gap = 8.0 * scale, 14.0 * scale
    west = routes.ellipse((-gap, 0.0), r, r, start_deg=-90.0)
    east = routes.ellipse((gap, 0.0), r, r, start_deg=-90.0)
    bridge = routes.turtle(
        (-gap, -r), 0.0, [("arc", r, 90.0), ("arc", gap - r, -180.0), ("arc", r, 180.0)]
    )
    laps = params["laps"]
    sessions = [
        _session("session1", 1, west, 0.0, laps * west.length, info=_laps_info(west, laps * west.length, 0.5)),
        _session("session2", 2, east, 0.0, laps * east.length, info=_laps_info(east, laps * east.length, 0.5)),
        _session(
            "session3", 3, bridge, 0.0, bridge.length,
            info={"overlap_m": {"session1": round(0.5 * math.pi * r, 3), "session2": round(math.pi * r, 3)}},
        ),
    ]
    return _ground_plan("bridge", seed, params, [west, east, bridge], sessions, None, scale)


def build_chain5(seed: int, scale: float, params: dict[str, float]) -> Plan:
    """Four inner loops and one outer loop touching them (as the iRat sessions of Menezes et al.).

    Inner loops: 12 m × 12 m rounded squares (corner radius 3 m) centred at (±8, ±8) m, counter-clockwise.
    The outer loop, a 28 m × 28 m rounded square around them, runs along the outer two sides and the outer
    corner of each inner loop in the same direction. ``session1``..``session4`` drive ``laps`` laps of the
    inner loops, ``session5`` ``laps`` laps of the outer one.
    """
    side, half_gap, radius = 12.0 * scale, 10.0 * scale, 3.0 * scale
    centres = [(half_gap, half_gap), (-half_gap, half_gap), (-half_gap, -half_gap), (half_gap, -half_gap)]
    starts = ["left", "bottom", "right", "top"]  # the inner side of each square, shared with nobody
    inner = [routes.rounded_rectangle(c, side, side, radius, start=st) for c, st in zip(centres, starts, strict=True)]
    outer = routes.rounded_rectangle((0.0, 0.0), 2 * half_gap + side, 2 * half_gap + side, radius, start="bottom")
    laps = params["laps"]
    sessions = [
        _session(f"session{k + 1}", k + 1, route, 0.0, laps * route.length,
                 info=_laps_info(route, laps * route.length, GROUND_SPEED))
        for k, route in enumerate(inner)
    ]
    sessions.append(
        _session("session5", 5, outer, 0.0, laps * outer.length,
                 info=_laps_info(outer, laps * outer.length, GROUND_SPEED))
    )
    return _ground_plan("chain5", seed, params, [*inner, outer], sessions, None, scale)


ALIAS_TURN_RADIUS = 1.5
"""Radius of the quarter turns at the ends of the look-alike stretch; also the corridor half-width there."""
ALIAS_LEG = 3.0
"""Straight length of the corridor legs leading to and from the stretch."""
ALIAS_EXIT = 2.5
"""Length of the exit corridors of the look-alike structure."""
ALIAS_WALL_HEIGHT = 4.5


def _alias_structure(builder: WorldBuilder, centre: tuple[float, float], stretch: float, scale: float) -> list[int]:
    """Add the walled "H" around a look-alike stretch centred at ``centre`` (stretch along +x).

    A corridor (half-width ``ALIAS_TURN_RADIUS``) holds the stretch; at each end it meets a cross corridor
    whose legs run ``ALIAS_LEG`` m north and south and then turn outwards into exit corridors. The walls
    are tall and the legs turn away, so from the stretch nothing outside the structure is visible. A route
    through it comes down (or up) one leg, drives the stretch eastwards and leaves by the other end's leg.
    """
    w = ALIAS_TURN_RADIUS * scale
    e = stretch / 2 + w  # centre line of the cross corridors
    y_exit = 2 * w + ALIAS_LEG * scale  # centre line of the exit corridors
    x_end = e + w + ALIAS_EXIT * scale
    cx, cy = centre
    segments: list[tuple[tuple[float, float], tuple[float, float]]] = []
    for sy in (1.0, -1.0):
        segments.append(((-(e - w), sy * w), (e - w, sy * w)))  # stretch walls
        for sx in (1.0, -1.0):
            segments.append(((sx * (e - w), sy * w), (sx * (e - w), sy * (y_exit + w))))  # inner leg wall
            segments.append(((sx * (e - w), sy * (y_exit + w)), (sx * x_end, sy * (y_exit + w))))  # exit, far
            segments.append(((sx * (e + w), sy * 0.0), (sx * (e + w), sy * (y_exit - w))))  # outer leg wall
            segments.append(((sx * (e + w), sy * (y_exit - w)), (sx * x_end, sy * (y_exit - w))))  # exit, near
    return [
        builder.add_wall((cx + p[0], cy + p[1]), (cx + q[0], cy + q[1]), top=builder.floor_z + ALIAS_WALL_HEIGHT)
        for p, q in segments
    ]


def build_aliased(seed: int, scale: float, params: dict[str, float]) -> Plan:
    """Two distinct places that look alike: two sessions over disjoint regions with one look-alike stretch.

    Region A (west) is a counter-clockwise loop, region B (east, 40 m away) a clockwise loop of other
    proportions (:func:`~.routes.notched_loop`). Each dips into a notch where the vehicle drives a straight
    ``alias_length_m`` long eastwards between two tight quarter turns (radius 1 m): in A it comes down into
    the notch from the north and leaves northwards (left turns), in B it comes up from the south and leaves
    southwards (right turns). Both notches run through identical walled structures (:func:`_alias_structure`,
    the same walls with the same textures): a corridor holding the stretch, with cross corridors at both
    ends whose legs turn away, so from the stretch nothing outside the structure can be seen. On the
    stretch the two places therefore look alike up to the per-visit noise (lighting, lateral offset, pixel
    noise); one frame (0.5 m) before or after it the vehicles are in the turns, their headings differ by
    about 60° and A sees up one leg where B sees down the other, so the views stop matching. At 0.5 m per
    frame the default 1 m stretch holds 2 frames (3 when a frame falls exactly on its start). Each session
    starts half a lap away from its stretch and passes it once per lap; ``alias`` in scenario.json gives the
    stretch as arc lengths driven by each session.
    """
    alias = params["alias_length_m"]
    if alias < 0:
        msg = f"alias_length_m must be ≥ 0, got {alias!r}"
        raise InputError(msg)
    half_span = (alias / 2 + 2 * ALIAS_TURN_RADIUS + ALIAS_EXIT) * scale
    centre_a = (-(half_span + 20.0 * scale), 0.0)
    centre_b = (half_span + 20.0 * scale, 0.0)
    notch = {
        "corner": 3.0 * scale,
        "notch_depth": ALIAS_LEG * scale,
        "notch_radius": ALIAS_TURN_RADIUS * scale,
    }
    region_a = routes.notched_loop(centre_a, alias, side=6.0 * scale, height=8.0 * scale, ccw=True, **notch)
    region_b = routes.notched_loop(centre_b, alias, side=5.0 * scale, height=11.0 * scale, ccw=False, **notch)
    reach = half_span + 1.5 * scale
    discs = ((centre_a[0], centre_a[1], reach), (centre_b[0], centre_b[1], reach))
    builder = _ground_world(seed, [region_a, region_b], exclude=discs)
    walls = _alias_structure(builder, centre_a, alias, scale)
    builder.copy_surfaces(walls, (centre_b[0] - centre_a[0], centre_b[1] - centre_a[1]))
    laps = params["laps"]
    start_a = region_a.length / 2
    start_b = region_b.length / 2
    sessions = [
        _session("session1", 1, region_a, start_a, laps * region_a.length,
                 info=_laps_info(region_a, laps * region_a.length, GROUND_SPEED)),
        _session("session2", 2, region_b, start_b, laps * region_b.length,
                 info=_laps_info(region_b, laps * region_b.length, GROUND_SPEED)),
    ]
    # The routes start at the middle of their stretches; the sessions start half a lap later.
    info = {
        "alias": {
            "length_m": alias,
            "centres": [list(centre_a), list(centre_b)],
            "session1_arc_m": [region_a.length / 2 - alias / 2, region_a.length / 2 + alias / 2],
            "session2_arc_m": [region_b.length / 2 - alias / 2, region_b.length / 2 + alias / 2],
        }
    }
    return _ground_plan("aliased", seed, params, [region_a, region_b], sessions, None, scale, info, builder)


def check_switches(params: Mapping[str, float], names: tuple[str, ...]) -> None:
    """Refuse a switch parameter that is not 0 or 1.

    Raises:
        InputError: one of ``names`` is neither 0 nor 1.
    """
    for name in names:
        if params[name] not in (0.0, 1.0):
            msg = f"{name} must be 0 or 1, got {params[name]!r}"
            raise InputError(msg)


def build_cave3d(seed: int, scale: float, params: dict[str, float]) -> Plan:
    """An underwater cave loop (ellipse 3 m × 1.8 m semi-axes) whose depth changes along the way (4-DoF).

    Depth ``z = −1.5 + depth_amplitude_m · sin(2·2π·s/L)`` (two dives per lap). ``single``: ``single_laps``
    laps from the start; ``session1``: ``session1_laps`` laps from the start; ``session2`` starts half a
    lap further and runs ``session2_laps`` laps, overlapping session 1.
    """
    route = routes.ellipse((0.0, 0.0), 3.0 * scale, 1.8 * scale, start_deg=0.0)
    length = route.length
    amplitude = params["depth_amplitude_m"]
    check_switches(params, ("nav", "odometry"))
    if params["sonar"] not in (0.0, 1.0) or not params["turbidity"] >= 0.0:
        msg = f"sonar must be 0 or 1 and turbidity ≥ 0, got {params['sonar']!r} and {params['turbidity']!r}"
        raise InputError(msg)

    def depth(s: FloatArray) -> FloatArray:
        return -1.5 + amplitude * np.sin(2.0 * 2.0 * math.pi * np.asarray(s) / length)

    rng = np.random.default_rng([seed, 0])
    builder = WorldBuilder(seed, texels_per_m=40.0, feature_m=0.15, floor_z=-3.0, ceiling_z=0.0,
                           floor_albedo=0.35, ceiling_albedo=0.7)
    keep = route.points(0.05)
    builder.line_route(rng, route.xy[:-1], keep, offset=0.7, clearance=0.6, panel=(0.3, 0.9), gap=(0.05, 0.4),
                       height=(3.0, 3.0))
    lo, hi = keep.min(axis=0) - 2.0, keep.max(axis=0) + 2.0
    builder.scatter_boxes(rng, keep, (lo[0], lo[1], hi[0], hi[1]), density=2.0, clearance=1.0,
                          size=(0.1, 0.35), height=(0.5, 3.0))
    world = builder.build()
    d1, d2, ds = (params[k] * length for k in ("session1_laps", "session2_laps", "single_laps"))
    sessions = [
        _session("session1", 1, route, 0.0, d1, speed=CAVE_SPEED, depth=depth,
                 info=_laps_info(route, d1, CAVE_SPEED)),
        _session("session2", 2, route, 0.5 * length, d2, speed=CAVE_SPEED, depth=depth,
                 info={**_laps_info(route, d2, CAVE_SPEED), "start_m": round(0.5 * length, 3)}),
    ]
    single = _session("single", 0, route, 0.0, ds, speed=CAVE_SPEED, depth=depth,
                      info=_laps_info(route, ds, CAVE_SPEED))
    return Plan(
        scenario="cave3d",
        preset="poseidon",
        world=world,
        camera=dataclasses.replace(CAVE_CAMERA, fog_length=CAVE_CAMERA.fog_length / (1.0 + params["turbidity"])),
        rates=CAVE_RATES,
        noise=CAVE_NOISE.scaled(min(scale, 1.0)),
        sessions=tuple(sessions),
        single=single,
        params=params,
        sonar=Sonar() if params["sonar"] == 1.0 else None,
        navigation=NavSensors() if params["nav"] == 1.0 else None,
        odometry=params["odometry"] == 1.0,
    )


# The look-alike scenarios build on this module's helpers; the package imports this module first, so
# lookalike finds them defined when it imports them.
from mapserver.ingest.simulator import building as _building  # noqa: E402
from mapserver.ingest.simulator import lookalike as _lookalike  # noqa: E402
from mapserver.ingest.simulator import seabed as _seabed  # noqa: E402
from mapserver.ingest.simulator import street as _street  # noqa: E402

SCENARIOS: Mapping[str, ScenarioDef] = {
    d.name: d
    for d in (
        ScenarioDef("loop", "one session, two laps of a rounded-rectangle loop", {"laps": 2.0}, build_loop),
        ScenarioDef("figure8", "one session, two laps of a figure-eight", {"laps": 2.0}, build_figure8),
        ScenarioDef(
            "ellipse",
            "Virtual Tour: one 2.5-lap session, and a split (3/4 lap; then 3 laps from an unmapped place)",
            {"single_laps": 2.5, "session1_laps": 0.75, "session2_start": 0.875, "session2_laps": 3.0,
             "heading_offset_deg": 0.0},
            build_ellipse,
        ),
        ScenarioDef("bridge", "two loops mapped separately and a session connecting them", {"laps": 1.25},
                    build_bridge),
        ScenarioDef("chain5", "four inner loops and one outer loop touching them", {"laps": 1.1}, build_chain5),
        ScenarioDef("cave3d", "underwater cave loop with depth changes, two overlapping sessions (4-DoF)",
                    {"single_laps": 2.0, "session1_laps": 1.5, "session2_laps": 1.5, "depth_amplitude_m": 0.4,
                     "sonar": 0.0, "turbidity": 0.0, "nav": 0.0, "odometry": 1.0},
                    build_cave3d),
        ScenarioDef("aliased", "two distinct places that look alike for a short stretch",
                    {"laps": 1.1, "alias_length_m": 0.25}, build_aliased),
        *_lookalike.DEFINITIONS,
        *_street.DEFINITIONS,
        *_building.DEFINITIONS,
        *_seabed.DEFINITIONS,
    )
}

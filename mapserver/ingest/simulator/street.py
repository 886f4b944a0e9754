"""The ``street`` scenario: laps of a city block between repeated façades, seen by a forward camera.

The route is a rounded rectangle around a block (``block_w_m`` × ``block_h_m``, corner radius 3 m), driven
counter-clockwise. Both sides of the street (``street_m`` between the façades) are lined with buildings
(:meth:`~.world.WorldBuilder.facades`): each building is 2–6 façade bays of 3 m, all showing one texture
of a small ``palette`` of window bays, 4–12 m tall, with 0.5–4 m side streets between buildings, so the same
façade repeats along a building and along the street — the look-alike views a street gives a forward
camera. Street furniture (kiosks, bins, parked vans: boxes 0.4–1.6 m across, 0.8–2.5 m tall) stands between
the lane and the façades, about one per 4 m of street, and tells places apart where the façades do not.

The vehicle carries a forward camera (:mod:`.sensors`): ``fov_deg`` across 160 × 120 square pixels,
``camera_hz`` frames written as JPEG of ``jpeg_quality``, wheel odometry at ``odom_hz`` with the vehicle's
``scale_error`` and ``yaw_bias`` magnitudes, driving at ``speed``. ``light_turn_deg`` and ``light_gain``
change the light by that much per lap (the sun's direction, and the exposure as a fraction). One session,
``single``, drives ``laps`` laps.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from mapserver.errors import InputError
from mapserver.ingest.simulator import routes
from mapserver.ingest.simulator.scenarios import (
    GROUND_SPEED,
    Plan,
    ScenarioDef,
    _ground_plan,
    _laps_info,
    _session,
)
from mapserver.ingest.simulator.sensors import Sensors, fit_sensors
from mapserver.ingest.simulator.world import WorldBuilder

BAY_M = 3.0
"""Width of one façade bay (one window per storey)."""
BUILDING_HEIGHT = (4.0, 12.0)
CORNER_M = 3.0
FURNITURE_EVERY_M = 4.0


def _street_furniture(builder: WorldBuilder, rng: np.random.Generator, route: routes.Route, half_street: float) -> None:
    """Stand boxes between the lane and the façades on both sides, about one per ``FURNITURE_EVERY_M`` metres."""
    count = int(route.length / FURNITURE_EVERY_M)
    arcs = np.sort(rng.uniform(0.0, route.length, count))
    sides = np.where(rng.random(count) < 0.5, -1.0, 1.0)
    for s, side in zip(arcs.tolist(), sides.tolist(), strict=True):
        half_x, half_y = float(rng.uniform(0.2, 0.8)), float(rng.uniform(0.2, 0.5))
        lateral = side * float(rng.uniform(1.7 + half_y, max(1.8 + half_y, half_street - 0.4 - half_y)))
        centre = route.position(s) + lateral * route.normal(s)
        angle = float(route.heading(s)) + float(rng.normal(0.0, 0.1))
        builder.add_box(tuple(centre), half_x, half_y, angle, builder.floor_z + float(rng.uniform(0.8, 2.5)))


def build_street(seed: int, scale: float, params: dict[str, float]) -> Plan:
    """Build the ``street`` plan (module docstring)."""
    width, height, street = params["block_w_m"] * scale, params["block_h_m"] * scale, params["street_m"]
    if min(width, height) <= 2 * CORNER_M * scale or street < 4.0 or params["palette"] < 1:
        msg = f"the block must be wider than its corners, the street at least 4 m and the palette ≥ 1: {params!r}"
        raise InputError(msg)
    route = routes.rounded_rectangle((0.0, 0.0), width, height, CORNER_M * scale)
    rng = np.random.default_rng([seed, 0])
    builder = WorldBuilder(seed, texels_per_m=10.0, feature_m=0.5, floor_albedo=0.3)
    palette = [builder.add_texture(BAY_M, BUILDING_HEIGHT[1], "windows") for _ in range(int(params["palette"]))]
    keep = route.points(0.25)
    builder.facades(rng, route, keep, offset=street / 2, palette=palette, module_m=BAY_M, modules=(2, 6),
                    gap=(0.5, 4.0), height=BUILDING_HEIGHT)  # fmt: skip
    _street_furniture(builder, rng, route, street / 2)
    distance = params["laps"] * route.length
    single = _session("single", 0, route, 0.0, distance, info=_laps_info(route, distance, GROUND_SPEED))
    plan = _ground_plan("street", seed, params, [route], [single], single, scale, builder=builder)
    sensors = Sensors(
        fov_deg=params["fov_deg"], camera_hz=params["camera_hz"], odom_hz=params["odom_hz"], speed=params["speed"],
        jpeg_quality=int(params["jpeg_quality"]), light_turn_deg=params["light_turn_deg"],
        light_gain=params["light_gain"], scale_error=params["scale_error"], yaw_bias=params["yaw_bias"],
    )  # fmt: skip
    return dataclasses.replace(fit_sensors(plan, sensors), preset="forward")


DEFAULTS = {
    "laps": 2.0, "block_w_m": 36.0, "block_h_m": 20.0, "street_m": 9.0, "palette": 5.0,
    "fov_deg": 75.0, "camera_hz": 10.0, "odom_hz": 20.0, "speed": 1.0, "jpeg_quality": 80.0,
    "light_turn_deg": 0.0, "light_gain": 0.0, "scale_error": 0.025, "yaw_bias": 0.004,
}  # fmt: skip

DEFINITIONS: tuple[ScenarioDef, ...] = (
    ScenarioDef("street", "laps of a city block between repeated façades, forward camera, JPEG frames", DEFAULTS,
                build_street),
)

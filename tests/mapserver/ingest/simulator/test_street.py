"""The street world, the forward-camera sensors and a light that changes between laps."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mapserver.errors import InputError
from mapserver.ingest import open_log
from mapserver.ingest.simulator import WorldBuilder, plan_scenario, routes, simulate
from mapserver.ingest.simulator.render import Lighting
from mapserver.ingest.simulator.sensors import Sensors, fit_sensors
from mapserver.ingest.simulator.world import AMBIENT, LIGHT_DIRECTION


def test_facades_line_a_straight_street_with_bays_of_one_texture_per_building() -> None:
    route = routes.from_points(np.column_stack([np.linspace(0.0, 60.0, 3001), np.zeros(3001)]), closed=False)
    builder = WorldBuilder(3)
    palette = [builder.add_texture(3.0, 12.0, "windows") for _ in range(2)]
    walls = builder.facades(np.random.default_rng(0), route, route.points(0.25), offset=5.0, palette=palette,
                            module_m=3.0, modules=(2, 4), gap=(1.0, 2.0), height=(4.0, 8.0))  # fmt: skip
    world = builder.build()
    p0, p1 = world.p0[walls], world.p1[walls]
    assert np.allclose(np.abs(p0[:, 1]), 5.0) and np.allclose(p0[:, 1], p1[:, 1])  # both sides, 5 m off the route
    assert np.allclose(np.linalg.norm(p1 - p0, axis=1), 3.0)  # one bay each
    assert {int(v) for v in np.sign(p0[:, 1])} == {-1, 1}
    # every wall shows a palette texture; a building's bays (consecutive, touching) all show the same one
    textures = world.tex_offset[walls]
    assert set(textures.tolist()) == {0, builder.textures[0].size}  # the two palette textures, both drawn
    touching = np.linalg.norm(p1[:-1] - p0[1:], axis=1) < 1e-9
    assert touching.any()
    assert np.all(textures[:-1][touching] == textures[1:][touching])
    # most of the street is built: 2-4 bays of 3 m, then 1-2 m of gap
    left = p0[:, 1] > 0
    assert 3.0 * left.sum() > 0.7 * 60.0


def test_street_plans_a_forward_camera_with_jpeg_frames_and_clear_lanes() -> None:
    plan = plan_scenario("street", 2)
    assert plan.preset == "forward" and plan.single is not None and plan.sessions == (plan.single,)
    assert plan.camera.hfov_deg == 75.0 and (plan.camera.width, plan.camera.height) == (160, 120)
    assert (plan.rates.camera_hz, plan.rates.odom_hz) == (10.0, 20.0)
    assert plan.image_encoding == "jpeg" and plan.jpeg_quality == 80
    assert plan.single.spec.speed == 1.0
    route = plan.single.spec.route
    assert route.length == pytest.approx(2 * (36 + 20) - (8 - 2 * math.pi) * 3.0, rel=1e-3)
    walls = np.vstack([np.linspace(a, b, 20) for a, b in zip(plan.world.p0, plan.world.p1, strict=True)])
    nearest, _ = cKDTree(walls).query(route.points(0.1))
    assert nearest.min() > 1.45
    with pytest.raises(InputError, match="street at least 4 m"):
        plan_scenario("street", params={"street_m": 3.0})


def test_fit_sensors_replaces_the_camera_rates_speed_and_vehicle_errors_only() -> None:
    loop = plan_scenario("loop", 1)
    sensors = Sensors(fov_deg=50.0, camera_hz=7.0, odom_hz=40.0, speed=2.0, jpeg_quality=65, scale_error=0.04,
                      yaw_bias=0.01, light_turn_deg=60.0, light_gain=-0.3)  # fmt: skip
    fitted = fit_sensors(loop, sensors)
    assert fitted.world is loop.world and fitted.single is not None and loop.single is not None
    assert fitted.single.spec.route is loop.single.spec.route and fitted.single.spec.speed == 2.0
    assert fitted.camera.hfov_deg == 50.0 and (fitted.rates.camera_hz, fitted.rates.odom_hz) == (7.0, 40.0)
    assert (fitted.noise.scale_error, fitted.noise.yaw_bias) == (0.04, 0.01)
    assert fitted.noise.lateral_m == loop.noise.lateral_m
    lap_s = loop.single.spec.route.length / 2.0
    assert fitted.single.info["nominal_lap_s"][0] == pytest.approx(lap_s, abs=1e-3)
    assert fitted.lighting is not None
    assert fitted.lighting.turn_rad_per_s * lap_s == pytest.approx(math.radians(60.0))
    assert fitted.lighting.gain_per_s * lap_s == pytest.approx(-0.3)
    assert fit_sensors(loop, Sensors()).lighting is None  # a steady light unless asked
    with pytest.raises(ValueError, match="positive"):
        fit_sensors(loop, Sensors(speed=0.0))


def test_the_light_turns_the_faces_shade_and_the_exposure_falls_to_a_floor() -> None:
    builder = WorldBuilder(1)
    builder.add_wall((0.0, 0.0), (1.0, 0.0), top=1.0)  # normal ±y
    world = builder.build()
    sun = math.atan2(LIGHT_DIRECTION[1], LIGHT_DIRECTION[0])
    assert world.shade[0] == pytest.approx(AMBIENT + (1 - AMBIENT) * abs(math.sin(sun)))
    turned = world.lit(math.pi / 2 - sun)  # the sun straight along +y: the wall faces it
    assert turned.shade[0] == pytest.approx(1.0)
    assert world.lit(-sun).shade[0] == pytest.approx(AMBIENT)  # edge-on
    lighting = Lighting(turn_rad_per_s=0.01, gain_per_s=-0.01)
    lit, exposure = lighting.at(world, 50.0)
    assert exposure == pytest.approx(0.5) and lit.shade[0] == pytest.approx(world.lit(0.5).shade[0])
    assert lighting.at(world, 200.0)[1] == 0.25


def test_a_simulated_street_is_written_as_jpeg_of_its_quality_and_relit_between_laps(tmp_path: Path) -> None:
    small = {"laps": 0.3, "block_w_m": 16.0, "block_h_m": 10.0, "camera_hz": 4.0}
    sizes = {}
    for quality in (60, 95):
        folder = tmp_path / f"q{quality}"
        simulate("street", folder, seed=4, params={**small, "jpeg_quality": quality})
        with open_log(folder / "single.bag") as opened:
            frames = list(opened.frames())
            assert opened.mapping.as_dict()["image"] == "/robot/camera/image"
        assert frames and frames[0].image.shape == (120, 160)
        sizes[quality] = (folder / "single.bag").stat().st_size
    assert sizes[60] < 0.8 * sizes[95]  # compressed frames: JPEG at 60 is smaller than at 95
    dark = tmp_path / "dark"
    simulate("street", dark, seed=4, params={**small, "light_gain": -0.9, "laps": 0.6})
    with open_log(dark / "single.bag") as opened:
        frames = list(opened.frames())
    first, last = frames[0].image.mean(), frames[-1].image.mean()
    assert last < 0.75 * first  # the exposure fell over the lap

"""The ray caster against hand-computed scenes: wall extent, shading, occlusion, rotation, camera height."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapserver.ingest.simulator import Camera, WorldBuilder, expose, render
from mapserver.ingest.simulator.world import AMBIENT, LIGHT_DIRECTION

CLEAR = {"fog_length": 1e9, "max_range": 100.0, "fade": 1e-6, "fog_level": 0.9}


def _world(walls: list[tuple[tuple[float, float], tuple[float, float], float]], albedo: object = 0.5) -> object:
    builder = WorldBuilder(1, texels_per_m=10.0, floor_albedo=0.2)
    for p0, p1, top in walls:
        builder.add_wall(p0, p1, top=top)
    for k, texture in enumerate(builder.textures):
        rows = np.arange(texture.shape[0])[:, None] / 10.0  # v in metres
        texture[:] = albedo(rows, k) if callable(albedo) else albedo
    return builder.build()


def test_wall_ahead_spans_the_hand_computed_rows_with_lambert_shade() -> None:
    d, height = 4.0, 2.0
    world = _world([((d, -20.0), (d, 20.0), height)])
    camera = Camera(width=360, height=60, hfov_deg=360.0, mount_height=1.0, **CLEAR)
    image = render(world, camera, 0.0, 0.0, 0.0, 0.0)
    shade = AMBIENT + (1 - AMBIENT) * abs(LIGHT_DIRECTION[0])  # the wall's normal is ±x
    centre = 179  # azimuth +0.5°: t = d / cos(0.5°)
    t = d / math.cos(math.radians(0.5))
    z = 1.0 + t * camera.slopes
    on_wall = (z >= 0.0) & (z <= height)
    assert on_wall.any() and (~on_wall).any()
    assert np.allclose(image[on_wall, centre], 0.5 * shade)
    above = ~on_wall & (camera.slopes > 0)
    assert np.allclose(image[above, centre], 0.9)  # sky: fog colour
    behind = image[:, 0]  # looking backwards: no wall, floor below the horizon, sky above
    assert np.allclose(behind[camera.slopes > 0], 0.9)
    floor_distance = np.where(camera.slopes < 0, 1.0 / -np.minimum(camera.slopes, -1e-12), np.inf)
    seen = floor_distance * np.sqrt(1 + camera.slopes**2) < 100.0
    assert seen.sum() > 20
    assert np.allclose(behind[seen], 0.2)
    assert np.allclose(behind[(camera.slopes < 0) & ~seen], 0.9)  # floor beyond the range: fog


def test_short_near_wall_does_not_hide_the_tall_wall_behind_it() -> None:
    world = _world([((2.0, -1.0), (2.0, 1.0), 1.2), ((6.0, -10.0), (6.0, 10.0), 5.0)],
                   albedo=lambda rows, k: 0.3 if k == 0 else 0.8)
    camera = Camera(width=64, height=40, hfov_deg=90.0, mount_height=1.0, **CLEAR)
    image = render(world, camera, 0.0, 0.0, 0.0, 0.0)
    column = image[:, 31]
    shade = AMBIENT + (1 - AMBIENT) * abs(LIGHT_DIRECTION[0])
    near = (1.0 + 2.0 * camera.slopes <= 1.2) & (1.0 + 2.0 * camera.slopes >= 0.0)
    assert np.allclose(column[near], 0.3 * shade, atol=1e-6)
    above_near = ~near & (camera.slopes > 0)
    assert np.allclose(column[above_near], 0.8 * shade, atol=1e-6)  # the tall wall, not the sky


def test_turning_a_panoramic_camera_rolls_the_image() -> None:
    world = _world([((3.0, -4.0), (3.0, 2.0), 2.0), ((-1.0, 5.0), (4.0, 6.0), 3.0)], albedo=lambda r, k: 0.2 + 0.3 * k)
    camera = Camera(width=128, height=16, hfov_deg=360.0, **CLEAR)
    step = 2 * math.pi / camera.width
    base = render(world, camera, 0.3, -0.2, 0.0, 0.4)
    turned = render(world, camera, 0.3, -0.2, 0.0, 0.4 + 5 * step)
    assert np.allclose(turned, np.roll(base, 5, axis=1), atol=1e-9)


def test_camera_height_selects_the_part_of_the_wall_texture_seen() -> None:
    # albedo rises with height on the wall: the horizon row sees the wall at the camera's own height
    world = _world([((3.0, -10.0), (3.0, 10.0), 4.0)], albedo=lambda rows, k: 0.1 + 0.2 * rows)
    camera = Camera(width=180, height=41, hfov_deg=360.0, mount_height=0.0, **CLEAR)
    horizon = 20  # slope 0
    shade = AMBIENT + (1 - AMBIENT) * abs(LIGHT_DIRECTION[0])
    for z in (0.5, 1.5, 3.0):
        image = render(world, camera, 0.0, 0.0, z, 0.0)
        assert image[horizon, 89] == pytest.approx((0.1 + 0.2 * z) * shade, abs=1e-6)


def test_fog_and_range_limit_what_is_seen() -> None:
    world = _world([((5.0, -10.0), (5.0, 10.0), 4.0)], albedo=0.1)
    near = Camera(width=90, height=9, hfov_deg=360.0, mount_height=1.0, fog_length=5.0, max_range=20.0, fade=1.0,
                  fog_level=0.6)
    image = render(world, near, 0.0, 0.0, 0.0, 0.0)
    a = math.exp(-5.0 / math.cos(math.radians(2.0)) / 5.0)
    shade = AMBIENT + (1 - AMBIENT) * abs(LIGHT_DIRECTION[0])
    assert image[4, 44] == pytest.approx(0.1 * shade * a + 0.6 * (1 - a), rel=1e-6)
    blind = Camera(width=90, height=9, hfov_deg=360.0, mount_height=1.0, fog_length=5.0, max_range=4.0, fade=1.0,
                   fog_level=0.6)
    assert render(world, blind, 0.0, 0.0, 0.0, 0.0)[4, 44] == pytest.approx(0.6)


def test_expose_gain_noise_and_clipping() -> None:
    radiance = np.array([[0.0, 0.5, 1.0, 2.0]])
    rng = np.random.default_rng(0)
    assert expose(radiance, 1.0, 0.0, rng).tolist() == [[0, 128, 255, 255]]
    assert expose(radiance, 0.5, 0.0, rng).tolist() == [[0, 64, 128, 255]]
    noisy = expose(np.full((200, 200), 0.5), 1.0, 2.0, rng).astype(float)
    assert noisy.std() == pytest.approx(2.0, rel=0.05)

"""The simulated imaging sonar against hand-computed scenes, and cave3d's sonar logs (issue 17, sonar modality)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mapserver.errors import InputError
from mapserver.ingest.reader import open_log
from mapserver.ingest.simulator import WorldBuilder, simulate
from mapserver.ingest.simulator.output import plan_scenario
from mapserver.ingest.simulator.render import Sonar, expose_sonar, render_sonar


def _wall_world(d: float, albedo: float = 0.6) -> object:
    """One wall across the x axis at x = d, floor 1 m below the sonar, no ceiling."""
    builder = WorldBuilder(1, texels_per_m=10.0, floor_z=-1.0, floor_albedo=0.3)
    builder.add_wall((d, -50.0), (d, 50.0), top=50.0, base=-50.0)
    for texture in builder.textures:
        texture[:] = albedo
    return builder.build()


def test_a_wall_ahead_echoes_in_its_range_bin_with_lambert_backscatter() -> None:
    d = 2.3
    sonar = Sonar(beams=3, bins=50, hfov_deg=30.0, vfov_deg=4.0, elevation_rays=2, max_range=5.0)
    echo = render_sonar(_wall_world(d), sonar, 0.0, 0.0, 0.0, 0.0)  # floor at 1 m: beyond 5 m at ±1°
    centre = echo[:, 1]  # azimuth 0: every ray meets the wall at 3-D range d / cos(±1°)
    r = d / math.cos(math.radians(1.0))
    row = sonar.bins - 1 - int(r / sonar.max_range * sonar.bins)  # far at the top
    assert np.flatnonzero(centre).tolist() == [row]
    assert centre[row] == pytest.approx(0.6 * math.cos(math.radians(1.0)))  # albedo · cos i, both rays
    side = echo[:, 0]  # azimuth +10°: range d / cos 10° / cos 1°, incidence cos 10° · cos 1°
    r_side = d / math.cos(math.radians(10.0)) / math.cos(math.radians(1.0))
    assert np.flatnonzero(side).tolist() == [sonar.bins - 1 - int(r_side / sonar.max_range * sonar.bins)]
    assert side.sum() == pytest.approx(0.6 * math.cos(math.radians(10.0)) * math.cos(math.radians(1.0)))


def test_a_wall_out_of_range_is_not_seen_but_the_floor_is_where_a_beam_meets_it() -> None:
    sonar = Sonar(beams=1, bins=10, hfov_deg=1.0, vfov_deg=60.0, elevation_rays=2, max_range=5.0)
    echo = render_sonar(_wall_world(8.0), sonar, 0.0, 0.0, 0.0, 0.0)  # rays at ±15°
    floor_range = 1.0 / math.sin(math.radians(15.0))  # 3.86 m down to the floor
    assert np.flatnonzero(echo[:, 0]).tolist() == [sonar.bins - 1 - int(floor_range / 5.0 * sonar.bins)]
    assert echo[:, 0].sum() == pytest.approx(0.3 * math.sin(math.radians(15.0)) / 2)  # one of the two rays


def test_speckle_keeps_the_mean_and_zero_stays_zero() -> None:
    sonar = Sonar(gain=0.5, speckle_looks=4.0)
    echo = np.zeros((200, 300))
    echo[:, :150] = 0.8
    image = expose_sonar(echo, sonar, np.random.default_rng(0))
    assert image.dtype == np.uint8 and not image[:, 150:].any()
    assert image[:, :150].mean() == pytest.approx(0.8 * 0.5 * 255, rel=0.02)
    assert image[:, :150].std() == pytest.approx(0.8 * 0.5 * 255 / 2, rel=0.05)  # gamma(4): std/mean = 1/2


def _images(path: Path, topic: str) -> list[np.ndarray]:
    with open_log(path, {"image": topic}) as log:
        return [np.array(frame.image, copy=True) for frame in log.frames()]


def test_cave3d_writes_a_sonar_topic_at_the_camera_stamps_and_leaves_the_camera_as_it_was(tmp_path: Path) -> None:
    plain = simulate("cave3d", tmp_path / "plain", seed=2, scale=0.3, only=["session1"])
    sonar = simulate("cave3d", tmp_path / "sonar", seed=2, scale=0.3, only=["session1"], params={"sonar": 1})
    assert "sonar" not in plain and sonar["sonar"]["topic"] == "/robot/sonar/image"
    cam_a = _images(tmp_path / "plain" / "session1.bag", "/robot/camera/image")
    cam_b = _images(tmp_path / "sonar" / "session1.bag", "/robot/camera/image")
    echoes = _images(tmp_path / "sonar" / "session1.bag", "/robot/sonar/image")
    assert len(cam_a) == len(cam_b) == len(echoes) == sonar["sessions"][0]["frames"]
    assert all(np.array_equal(a, b) for a, b in zip(cam_a, cam_b, strict=True))  # same camera, bit for bit
    assert echoes[0].shape == (48, 64) and all(e.any() for e in echoes)  # the cave's walls always echo


def test_turbidity_fogs_the_camera_not_the_sonar() -> None:
    clear, murky = (plan_scenario("cave3d", 0, params={"sonar": 1, "turbidity": t}) for t in (0.0, 3.0))
    assert murky.camera.fog_length == pytest.approx(clear.camera.fog_length / 4.0)
    assert murky.sonar == clear.sonar
    with pytest.raises(InputError, match="sonar must be 0 or 1"):
        plan_scenario("cave3d", 0, params={"sonar": 2})

"""OpenRatSLAM's scanline-intensity visual odometry on synthetic shifted profiles."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.config import Params
from core.visual_odometry import VisualOdometry, best_shift, column_profile


def _strip(width: int, seed: int = 0) -> np.ndarray:
    """A 1-D texture with distinct columns."""
    return np.random.default_rng(seed).integers(20, 235, width).astype(np.float64)


def test_column_profile_is_the_column_mean_over_255() -> None:
    grey = np.array([[0, 51, 102], [102, 153, 204]], dtype=np.float64)
    assert column_profile(grey, 0, -1, 0, -1) == pytest.approx(np.array([51, 102, 153]) / 255)
    assert column_profile(grey, 1, 3, 1, 2) == pytest.approx(np.array([153, 204]) / 255)


@pytest.mark.parametrize("shift", [-7, -1, 0, 3, 12])
def test_best_shift_recovers_a_known_shift(shift: int) -> None:
    strip = _strip(120)
    previous = strip[20:100] / 255
    current = strip[20 - shift : 100 - shift] / 255  # the scene moved by `shift` columns towards higher x
    found, diff = best_shift(current, previous)
    assert found == shift
    assert diff == pytest.approx(0.0, abs=1e-12)


def test_best_shift_searches_39_columns_each_way() -> None:
    strip = _strip(200, seed=1)
    previous = strip[50:150] / 255
    found, _ = best_shift(strip[50 - 39 : 150 - 39] / 255, previous)
    assert found == 39
    found, diff = best_shift(strip[50 - 45 : 150 - 45] / 255, previous)  # beyond the search range
    assert found != 45 and diff > 0


def test_best_shift_prefers_openratslam_order_on_ties() -> None:
    flat = np.full(30, 0.5)
    assert best_shift(flat, flat) == (0, 0.0)  # every shift ties: 0 is tried first
    previous = np.tile([0.1, 0.9, 0.4, 0.7, 0.2], 8)  # period 5
    current = np.roll(previous, 1)  # shifts +1 and −4 both line up exactly
    assert best_shift(current, previous) == (-4, 0.0)  # all negative shifts are tried before positive ones


def test_rotation_and_speed_from_a_shifted_image() -> None:
    """vrot = shift · fov / image width · rate, vtrans = min difference · scaling (capped)."""
    width, height = 160, 40
    params = Params().replace(
        vrot_image_x_min=40, vrot_image_x_max=120, vtrans_image_x_min=40, vtrans_image_x_max=120,
        camera_fov_deg=80.0, vtrans_scaling=100.0, vtrans_max=20.0,
    )
    strip = _strip(400, seed=2)
    first = np.tile(strip[100 : 100 + width], (height, 1)).astype(np.uint8)
    second = np.tile(strip[100 - 4 : 100 - 4 + width], (height, 1)).astype(np.uint8)  # scene moved 4 px
    vo = VisualOdometry(params)
    assert vo.process(first, 0.0) == (0.0, 0.0)  # first frame: nothing to compare with
    vtrans, vrot = vo.process(second, 0.25)
    # degrees per pixel from the whole image width (160 px), rate 1/dt = 4 Hz
    assert vrot == pytest.approx(4 * math.radians(80.0) / width * 4.0)
    assert vtrans == pytest.approx(0.0, abs=1e-12)  # a pure shift leaves no residual difference
    brighter = np.clip(second.astype(np.int64) + 10, 0, 255).astype(np.uint8)
    vtrans, _ = vo.process(brighter, 0.25)
    assert vtrans == pytest.approx(10 / 255 * 100.0, rel=1e-9)  # every column 10 grey levels brighter
    vo_capped = VisualOdometry(params.replace(vtrans_max=1.5))
    vo_capped.process(second, 0.25)
    assert vo_capped.process(brighter, 0.25)[0] == 1.5


def test_camera_rate_is_the_fallback_without_a_frame_interval() -> None:
    params = Params().replace(camera_fov_deg=50.0, camera_hz=10.0)
    strip = _strip(300, seed=3)
    vo = VisualOdometry(params)
    vo.process(np.tile(strip[50:170], (8, 1)).astype(np.uint8), 0.0)
    _, vrot = vo.process(np.tile(strip[48:168], (8, 1)).astype(np.uint8), 0.0)
    assert vrot == pytest.approx(2 * math.radians(50.0) / 120 * 10.0)  # current[k + 2] = previous[k]


def test_snapshot_round_trip() -> None:
    vo = VisualOdometry(Params())
    vo.process(np.tile(_strip(64), (4, 1)).astype(np.uint8), 0.0)
    back = VisualOdometry.restore(vo.params, vo.snapshot())
    assert np.array_equal(back.prev_vrot, vo.prev_vrot) and np.array_equal(back.prev_vtrans, vo.prev_vtrans)

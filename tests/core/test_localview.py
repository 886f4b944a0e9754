"""Local view templates (OpenRatSLAM convert_view_to_view_template / compare), hand-computed expectations."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from core.config import Params
from core.localview import LocalViewCells, patch_normalise
from tests.worlds import smooth_panorama

# grey levels of a 4 × 6 test image; the RGB version is (g − 9, g, g + 9), whose channel mean is g
GREY = np.array(
    [
        [10, 20, 30, 40, 50, 60],
        [70, 80, 90, 100, 110, 120],
        [130, 140, 150, 160, 170, 180],
        [190, 200, 210, 220, 230, 240],
    ],
    dtype=np.int64,
)
RGB = np.stack([GREY - 9, GREY, GREY + 9], axis=2).astype(np.uint8)


def _cells(**changes: object) -> LocalViewCells:
    return LocalViewCells(Params().replace(**changes))


def test_crop_greyscale_block_average() -> None:
    """Crop x 1..5 (4 columns), 2 × 2 blocks of 2 × 2 pixels, channel mean, /255."""
    cells = _cells(image_crop_x_min=1, image_crop_x_max=5, template_x_size=2, template_y_size=2)
    template, mean = cells.make_template(RGB)
    expected = np.array([[20 + 30 + 80 + 90, 40 + 50 + 100 + 110], [140 + 150 + 200 + 210, 160 + 170 + 220 + 230]])
    expected = expected / 4 / 255  # [[55, 75], [175, 195]] / 255
    assert template.dtype == np.float32
    assert template == pytest.approx(expected, abs=1e-7)
    assert mean == pytest.approx(125 / 255, abs=1e-7)


@given(
    shape=st.tuples(st.integers(1, 70), st.integers(1, 90)), cells=st.tuples(st.integers(1, 12), st.integers(1, 30)),
    deep=st.booleans(), seed=st.integers(0, 2**32 - 1),
)  # fmt: skip
@settings(max_examples=100, deadline=None)
def test_block_sums_of_whole_numbers_are_numpys_mean_bit_for_bit(
    shape: tuple[int, int], cells: tuple[int, int], deep: bool, seed: int
) -> None:
    """A mono image's blocks, summed a slice at a time, are numpy's mean over the block axes, to the bit."""
    from core.localview import block_average

    (h, w), (ty, tx) = shape, cells
    assume(h >= ty and w >= tx)
    rng = np.random.default_rng(seed)
    grey = rng.integers(0, 65536 if deep else 256, size=(h, w)).astype(np.float64)
    fast = block_average(grey, ty, tx, integral=True)
    by, bx = h // ty, w // tx
    expected = grey[: by * ty, : bx * tx].reshape(ty, by, tx, bx).mean(axis=(1, 3))
    assert fast.tobytes() == expected.tobytes()
    assert block_average(grey, ty, tx).tobytes() == expected.tobytes()


def test_leftover_pixels_past_the_last_block_are_dropped() -> None:
    """6 columns into 4 cells: block width 6 // 4 = 1, columns 4 and 5 unused (OpenRatSLAM integer blocks)."""
    cells = _cells(template_x_size=4, template_y_size=4)
    template, _ = cells.make_template(GREY.astype(np.uint8))
    assert template == pytest.approx(GREY[:, :4] / 255, abs=1e-7)


def test_global_normalisation_scales_to_the_target_mean_and_clips() -> None:
    cells = _cells(image_crop_x_min=1, image_crop_x_max=5, template_x_size=2, template_y_size=2, vt_normalisation=0.5)
    template, mean = cells.make_template(RGB)
    # v · 0.5 / mean with mean = 125/255: 55/250, 75/250, 175/250, 195/250
    assert template == pytest.approx(np.array([[0.22, 0.30], [0.70, 0.78]]), abs=1e-6)
    assert mean == pytest.approx(0.5, abs=1e-6)
    clipped = _cells(image_crop_x_min=1, image_crop_x_max=5, template_x_size=2, template_y_size=2, vt_normalisation=0.9)
    values, _ = clipped.make_template(RGB)
    assert values[1, 1] == pytest.approx(1.0)  # 195/125 · 0.9 = 1.404 → clipped to 1
    assert values[0, 0] == pytest.approx(55 / 125 * 0.9, abs=1e-6)


def test_patch_normalisation_replicates_the_border() -> None:
    """A single bright cell, radius 1: every patch has 9 samples, border cells repeated (OpenRatSLAM clamps)."""
    values = np.zeros((3, 3))
    values[1, 1] = 1.0
    out = patch_normalise(values, radius=1, min_std=0.0)
    # each 3 × 3 clamped patch holds exactly one sample of the bright cell: μ = 1/9, σ = √8/9
    centre = (3.0 + 2.0 * math.sqrt(2.0)) / 6.0  # ((1 − 1/9)/σ + 3)/6
    other = (3.0 - 1.0 / math.sqrt(8.0)) / 6.0  # ((0 − 1/9)/σ + 3)/6
    expected = np.full((3, 3), other)
    expected[1, 1] = centre
    assert out == pytest.approx(expected, abs=1e-12)


def test_patch_normalisation_flat_and_low_std_patches_are_one_half() -> None:
    flat = patch_normalise(np.full((4, 5), 0.3), radius=2, min_std=0.0)
    assert np.all(flat == 0.5)
    rng = np.random.default_rng(0)
    noisy = rng.random((4, 6))
    assert np.all(patch_normalise(noisy, radius=1, min_std=10.0) == 0.5)


def _patch_reference(values: np.ndarray, radius: int, min_std: float) -> np.ndarray:
    """Independent loop version of OpenRatSLAM's patch normalisation (clamped coordinates, (2r+1)² samples)."""
    h, w = values.shape
    out = np.empty_like(values)
    for y in range(h):
        for x in range(w):
            samples = [
                values[min(max(py, 0), h - 1), min(max(px, 0), w - 1)]
                for py in range(y - radius, y + radius + 1)
                for px in range(x - radius, x + radius + 1)
            ]
            mu = sum(samples) / len(samples)
            sigma = math.sqrt(sum((s - mu) ** 2 for s in samples) / len(samples))
            if sigma < min_std or sigma == 0.0:
                out[y, x] = 0.5
            else:
                out[y, x] = min(1.0, max(0.0, ((values[y, x] - mu) / sigma + 3.0) / 6.0))
    return out


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), radius=st.integers(1, 3), h=st.integers(1, 6), w=st.integers(1, 7))
def test_patch_normalisation_matches_the_loop_reference(seed: int, radius: int, h: int, w: int) -> None:
    values = np.random.default_rng(seed).random((h, w))
    assert patch_normalise(values, radius, 0.01) == pytest.approx(_patch_reference(values, radius, 0.01), abs=1e-9)


def _store(cells: LocalViewCells, templates: list[np.ndarray]) -> None:
    stack = np.stack(templates).astype(np.float32)
    cells.add_templates(stack, stack.reshape(len(templates), -1).mean(axis=1))


def test_template_matched_at_a_known_shift() -> None:
    """Shift 3: the view's columns [3, 9) are compared with the template's [o, o + 6) for o = 0..6."""
    rng = np.random.default_rng(1)
    stored = rng.uniform(0.2, 0.8, (3, 12)).astype(np.float32)
    cells = _cells(template_x_size=12, template_y_size=3, vt_shift_match=3, vt_step_match=1, vt_match_threshold=0.05)
    decoy = np.clip(stored + 0.3, 0, 1)
    _store(cells, [decoy, stored])
    for d in (-3, -1, 0, 2, 3):
        view = rng.uniform(0.2, 0.8, (3, 12)).astype(np.float32)
        view[:, 3:9] = stored[:, 3 + d : 9 + d]  # the scene moved by d columns
        view[:, 3:9] += 0.01  # and got a little brighter: error = mean |0.01| over the window
        best, error, rad = cells.match(view, float(stored.mean()))
        assert best == 1
        assert error == pytest.approx(0.01, abs=1e-6)
        assert rad == 0.0  # relative_rad is only measured for panoramic views


def test_a_shift_beyond_the_search_does_not_match() -> None:
    rng = np.random.default_rng(2)
    stored = rng.uniform(0.1, 0.9, (3, 12)).astype(np.float32)
    cells = _cells(template_x_size=12, template_y_size=3, vt_shift_match=2, vt_step_match=1, vt_match_threshold=0.03)
    _store(cells, [stored])
    view = np.roll(stored, 3, axis=1)  # 3 columns, the search covers ±2
    best, error, _ = cells.match(view, float(view.mean()))
    assert best == 0 and error > 0.03
    assert cells.match(view, float(view.mean()), limit=0.03) == (-1, math.inf, 0.0)


@pytest.mark.parametrize(
    ("offset", "expected_rad"), [(0, 0.0), (3, 3 / 8 * 2 * math.pi), (4, math.pi), (6, -math.pi / 2)]
)
def test_panoramic_relative_rad_at_a_known_circular_offset(offset: int, expected_rad: float) -> None:
    """The view is the template rotated by −offset columns: relative_rad = offset/X·2π wrapped to (−π, π]."""
    rng = np.random.default_rng(3)
    stored = rng.uniform(0.1, 0.9, (2, 8)).astype(np.float32)
    cells = _cells(template_x_size=8, template_y_size=2, vt_panoramic=True, vt_step_match=1, vt_match_threshold=0.03)
    _store(cells, [stored])
    view = np.roll(stored, -offset, axis=1)  # view column c shows template column c + offset
    best, error, rad = cells.match(view, float(view.mean()), limit=0.03)
    assert best == 0
    assert error == pytest.approx(0.0, abs=1e-7)
    assert rad == pytest.approx(expected_rad, abs=1e-12)


@pytest.mark.parametrize("pixels", [-8, -7, -3, 0, 1, 2, 5, 8])
def test_a_forward_views_column_shift_gives_its_heading_to_a_fraction_of_a_column(pixels: int) -> None:
    """``vt_shift_heading``: a 360° camera (256 pixels, 128 template columns) turned left by ``pixels`` pixel
    columns sees in column j what column j − pixels showed (the simulator's projection: column j looks along
    yaw + hfov/2 − (j + ½)·hfov/W), so its heading relative to the template is pixels · 2π/256; the match
    steps 2 columns from a shift of 5, so only the parabola through the best whole column and its
    neighbours finds it (within ±4 columns; at the search's edge, 5, it stops there). Off (OpenRatSLAM), a
    forward view has no heading offset."""
    image = smooth_panorama()
    params = {"template_x_size": 128, "template_y_size": 32, "vt_shift_match": 5, "vt_step_match": 2,
              "vt_match_threshold": 0.2, "camera_fov_deg": 360.0}  # fmt: skip
    for heading, expected in ((True, pixels * 2 * math.pi / 256), (False, 0.0)):
        cells = _cells(vt_shift_heading=heading, **params)
        cells.process(image)
        best, rad, created = cells.process(np.roll(image, pixels, axis=1))
        assert (best, created) == (0, False)
        assert rad == pytest.approx(expected, abs=0.1 * 2 * math.pi / 128)


@pytest.mark.parametrize("pixels", [-7, -2, 0, 3, 8])
def test_the_last_views_heading_against_a_template_is_its_column_shift_even_with_vt_shift_heading_off(
    pixels: int,
) -> None:
    """``view_heading`` (``merge_view_heading``): the match itself gives a forward view no offset (OpenRatSLAM),
    but asked for the last view's heading against template 0 it gives the same column shift ``vt_shift_heading``
    gives, pixels · 2π/256 (360°, 256 pixels); a panoramic view's offset comes from its match, so 0 there, and
    0 for a template that does not exist."""
    image = smooth_panorama()
    params = {"template_x_size": 128, "template_y_size": 32, "vt_shift_match": 10, "vt_step_match": 2,
              "vt_match_threshold": 0.2, "camera_fov_deg": 360.0}  # fmt: skip
    cells = _cells(**params)
    assert cells.view_heading(0) == 0.0  # no view yet
    cells.process(image)
    best, rad, created = cells.process(np.roll(image, pixels, axis=1))
    assert (best, rad, created) == (0, 0.0, False)
    assert cells.view_heading(0) == pytest.approx(pixels * 2 * math.pi / 256, abs=0.1 * 2 * math.pi / 128)
    assert cells.view_heading(1) == 0.0
    panoramic = _cells(**params, vt_panoramic=True)
    panoramic.process(image)
    panoramic.process(np.roll(image, pixels, axis=1))
    assert panoramic.view_heading(0) == 0.0


def test_a_stored_maps_matcher_knows_its_columns_heading_without_an_image() -> None:
    """A matcher rebuilt from stored templates (a stored map's places, an offline merge) has made no template:
    with the full width kept a column spans ``camera_fov_deg``/``template_x_size`` (360°/128), and a view turned
    by 3 pixels of 256 gets its heading 3·2π/256 from it, as the session that saw the image does. A crop of
    part of the width needs the image (100 of 200 pixels: half as much per column), so before one it is 0."""
    params = {"template_x_size": 128, "template_y_size": 32, "vt_shift_match": 5, "vt_step_match": 2,
              "vt_match_threshold": 0.2, "camera_fov_deg": 360.0, "vt_shift_heading": True}  # fmt: skip
    image = smooth_panorama()
    seen = _cells(**params)
    seen.process(image)
    stored = LocalViewCells.restore(seen.params, seen.snapshot())
    assert stored.column_rad == pytest.approx(2 * math.pi / 128) == seen.column_rad
    view, mean = seen.make_template(np.roll(image, 3, axis=1))
    best, _, rad = stored.match(view, mean)
    assert best == 0
    assert rad == pytest.approx(3 * 2 * math.pi / 256, abs=0.1 * 2 * math.pi / 128)
    cropped = _cells(**{**params, "template_x_size": 50, "image_crop_x_max": 100})
    assert cropped.column_rad == 0.0
    cropped.make_template(image[:, :200])
    assert cropped.column_rad == pytest.approx(math.radians(360.0) * 100 / 200 / 50)


def test_template_mean_prefilter_skips_templates_whose_mean_is_too_far() -> None:
    """The window matches exactly, but the unseen border columns move the template mean."""
    stored = np.tile(np.linspace(0.3, 0.6, 10, dtype=np.float32), (2, 1))
    params = {"template_x_size": 10, "template_y_size": 2, "vt_shift_match": 2, "vt_step_match": 1,
              "vt_match_threshold": 0.03}
    for delta, matches in [(0.085, True), (0.09, False)]:
        view = stored.copy()
        view[:, [0, 1, 8, 9]] += delta  # mean moves by 4·δ/10: 0.034 ≤ 0.03 + 0.005, 0.036 > it
        cells = _cells(**params)
        _store(cells, [stored])
        best, error, _ = cells.match(view, float(view.mean(dtype=np.float64)), limit=0.03)
        assert (best == 0) is matches
        if matches:
            assert error == pytest.approx(0.0, abs=1e-7)
    wide = _cells(**params, vt_mean_prefilter_epsilon=0.1)  # the same view passes a wider prefilter
    _store(wide, [stored])
    view = stored.copy()
    view[:, [0, 1, 8, 9]] += 0.09
    assert wide.match(view, float(view.mean(dtype=np.float64)))[0] == 0


def _compare_reference(cells: LocalViewCells, view: np.ndarray, mean: float) -> tuple[int, float, float]:
    """Independent loop version of OpenRatSLAM ``compare`` (first strict minimum over templates, then offsets)."""
    p = cells.params
    ty, tx = view.shape
    best, best_err, best_offset = -1, math.inf, 0
    for index in range(cells.count):
        template = cells.templates[index].astype(np.float64)
        if abs(mean - float(cells.means[index])) > p.vt_match_threshold + p.vt_mean_prefilter_epsilon:
            continue
        if p.vt_panoramic:
            for offset in range(0, tx, p.vt_step_match):
                total = sum(
                    abs(float(view[y, c]) - template[y, (c + offset) % tx]) for y in range(ty) for c in range(tx)
                )
                if total / (tx * ty) < best_err:
                    best, best_err, best_offset = index, total / (tx * ty), offset
        else:
            shift = p.vt_shift_match
            width = tx - 2 * shift
            for offset in range(0, 2 * shift + 1, p.vt_step_match):
                total = sum(
                    abs(float(view[y, shift + c]) - template[y, offset + c]) for y in range(ty) for c in range(width)
                )
                if total / (ty * width) < best_err:
                    best, best_err, best_offset = index, total / (ty * width), offset
    rad = 0.0
    if p.vt_panoramic and best >= 0:
        rad = best_offset / tx * 2 * math.pi
        rad = rad - 2 * math.pi if rad > math.pi else rad
    return best, best_err, rad


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 100_000), panoramic=st.booleans(), step=st.integers(1, 2), ty=st.sampled_from([3, 9]))
def test_vectorised_match_equals_the_loop_reference(seed: int, panoramic: bool, step: int, ty: int) -> None:
    # ty = 9: bands of 2–3 rows, so the band bound is a strict lower bound, not the error itself
    rng = np.random.default_rng(seed)
    tx, n = 10, 12
    cells = _cells(template_x_size=tx, template_y_size=ty, vt_shift_match=2, vt_step_match=step,
                   vt_panoramic=panoramic, vt_match_threshold=0.06)
    base = rng.uniform(0.2, 0.8, (n, ty, tx))
    base[: n // 2] = base[0] + rng.normal(0, 0.05, (n // 2, ty, tx))  # several near-duplicates: ties and near-ties
    _store(cells, list(np.clip(base, 0, 1)))
    source = cells.templates[int(rng.integers(n))].astype(np.float64)
    view = np.roll(source, int(rng.integers(-3, 4)), axis=1) + rng.normal(0, 0.03, (ty, tx))
    view = np.clip(view, 0, 1).astype(np.float32)
    mean = float(view.mean(dtype=np.float64))
    want = _compare_reference(cells, view, mean)
    got = cells.match(view, mean)
    assert got[0] == want[0]
    assert got[1] == pytest.approx(want[1], rel=1e-6)
    assert got[2] == pytest.approx(want[2])
    limited = cells.match(view, mean, limit=0.06)
    if want[1] <= 0.06 - 1e-6:
        assert limited[0] == want[0] and limited[1] == pytest.approx(want[1], rel=1e-6)
        assert limited[2] == pytest.approx(want[2])
    elif want[1] > 0.06 + 1e-6:
        assert limited == (-1, math.inf, 0.0)


def test_process_matches_or_creates() -> None:
    cells = _cells(template_x_size=6, template_y_size=4, vt_shift_match=1, vt_step_match=1, vt_match_threshold=0.02)
    image = GREY.astype(np.uint8)
    assert cells.process(image) == (0, 0.0, True)
    assert cells.process(image) == (0, 0.0, False)  # identical view: error 0
    other = (255 - GREY).astype(np.uint8)
    assert cells.process(other) == (1, 0.0, True)
    assert cells.count == 2 and (cells.current, cells.previous) == (1, 0)
    back = LocalViewCells.restore(cells.params, cells.snapshot())
    assert back.process(other) == (1, 0.0, False)  # the restored store (and its match bound) matches as before


def test_templates_beyond_unit_range_are_matched_after_a_fixed_point_rescale() -> None:
    """A template with values up to 3 (an imported map, not ours) lowers the fixed point's bits for all."""
    rng = np.random.default_rng(7)
    cells = _cells(template_x_size=60, template_y_size=2, vt_shift_match=2, vt_step_match=1, vt_match_threshold=0.05)
    small = rng.uniform(0.2, 0.8, (2, 60)).astype(np.float32)
    _store(cells, [small])
    assert cells._bits == 24
    large = (3.0 * rng.uniform(0.2, 0.9, (2, 60))).astype(np.float32)
    _store(cells, [large])
    assert cells._bits == 22  # 60 columns of differences up to 2·2.7 must fit a row sum in int32
    for index, stored in ((0, small), (1, large)):
        view = stored.copy()
        view[:, 2:58] += 0.01  # every compared value off by 0.01
        best, error, _ = cells.match(view, float(stored.mean()))
        assert best == index
        assert error == pytest.approx(0.01, abs=1e-5)


def _fixed_reference(templates: np.ndarray, bits: int, span: int) -> np.ndarray:
    """The matcher's fixed point computed in one piece in float64: round(v · 2^bits), panoramic rows wrapped."""
    fixed = np.rint(templates.astype(np.float64) * 2.0**bits).astype(np.int32)
    return np.concatenate([fixed, fixed[..., : span - fixed.shape[-1]]], axis=-1)


@pytest.mark.parametrize("panoramic", [False, True])
def test_a_restored_store_is_quantised_block_by_block_as_in_one_piece(panoramic: bool) -> None:
    """2·QUANTISE_ROWS + 37 templates, a block of them up to 2.5 in the middle: the restored fixed point is the
    float64 reference of the whole store at the bits of its peak (a row sum of 60 columns of |differences| up to
    2·2.5 fits int32 at 22 bits; the panoramic span of 119 columns at 21), and the matcher finds a stored template
    at error 0."""
    from core.localview import QUANTISE_ROWS

    n = 2 * QUANTISE_ROWS + 37
    rng = np.random.default_rng(11)
    templates = rng.uniform(0.0, 1.0, (n, 3, 60)).astype(np.float32)
    templates[600:700] *= np.float32(2.5)  # an imported map's values beyond [0, 1]: fewer bits for every row
    cells = _cells(template_x_size=60, template_y_size=3, vt_panoramic=panoramic)
    _store(cells, list(templates[:10]))
    assert cells._bits == (23 if panoramic else 24)  # before the large values arrive: (2^31 − 1)/(2 · span)
    back = LocalViewCells.restore(cells.params, {**cells.snapshot(), "lv_templates": templates,
                                                 "lv_means": templates.reshape(n, -1).mean(axis=1)})  # fmt: skip
    span = 119 if panoramic else 60
    bits = 21 if panoramic else 22
    assert back._bits == bits and math.floor(math.log2((2**31 - 1) / (2 * float(templates.max()) * span))) == bits
    np.testing.assert_array_equal(back._fixed.view, _fixed_reference(templates, bits, span))
    for index in (0, 650, n - 1):
        best, error, _ = back.match(templates[index], float(templates[index].mean()))
        assert (best, error) == (index, 0.0)


def test_restoring_a_large_store_holds_one_block_of_temporaries() -> None:
    """2,048 templates of 32 × 128 (32 MB in float32): the restore's traced peak is the two stores (the
    templates and their int32 fixed point, 32 MB each) and one block's float32 and int32 temporaries (8 MB
    each), not float64 copies of the whole store (64 MB each); the fixed point is still the reference's
    (22 bits: 2^31 − 1 over a row sum of 128 columns of |differences| ≤ 2 is just under 2^23)."""
    import tracemalloc

    rng = np.random.default_rng(5)
    templates = rng.random((2048, 32, 128), dtype=np.float32)
    params = Params().replace(template_x_size=128, template_y_size=32)
    state = {**LocalViewCells(params).snapshot(), "lv_templates": templates,
             "lv_means": templates.reshape(2048, -1).mean(axis=1)}  # fmt: skip
    tracemalloc.start()
    try:
        back = LocalViewCells.restore(params, state)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2 * 32 * 2**20 + 2 * 8 * 2**20 + 4 * 2**20
    assert back._bits == 22
    np.testing.assert_array_equal(back._fixed.view, _fixed_reference(templates, 22, 128))


def test_a_restored_store_keeps_the_snapshots_templates_array_and_appends_after_it() -> None:
    """2,048 templates of 32 × 128 (32 MB in float32): the restored store's templates are the snapshot's array
    itself, read-only, so the restore's traced peak is the int32 fixed point (32 MB) and one block's temporaries
    (8 MB each), with no float32 copy (32 MB more). A template made later goes after them: the snapshot's array
    is left as it was, and the store's snapshot joins both, equal to a store built in one piece."""
    import tracemalloc

    rng = np.random.default_rng(6)
    templates = rng.random((2048, 32, 128), dtype=np.float32)
    before = templates.copy()
    params = Params().replace(template_x_size=128, template_y_size=32)
    state = {**LocalViewCells(params).snapshot(), "lv_templates": templates,
             "lv_means": templates.reshape(2048, -1).mean(axis=1)}  # fmt: skip
    tracemalloc.start()
    try:
        back = LocalViewCells.restore(params, state)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 32 * 2**20 + 2 * 8 * 2**20 + 4 * 2**20
    assert np.shares_memory(back.templates, templates) and not back.templates.flags.writeable
    assert np.shares_memory(back.snapshot()["lv_templates"], templates)
    extra = rng.random((3, 32, 128), dtype=np.float32)
    back.add_templates(extra, extra.reshape(3, -1).mean(axis=1))
    np.testing.assert_array_equal(templates, before)
    whole = LocalViewCells(params)
    joined = np.concatenate([templates, extra])
    whole.add_templates(joined, joined.reshape(2051, -1).mean(axis=1))
    for key, value in whole.snapshot().items():
        np.testing.assert_array_equal(back.snapshot()[key], value, err_msg=key)
    np.testing.assert_array_equal(back._fixed.view, whole._fixed.view)
    with pytest.raises(ValueError, match="before rows are appended"):
        back.add_templates(extra, extra.reshape(3, -1).mean(axis=1), share=True)

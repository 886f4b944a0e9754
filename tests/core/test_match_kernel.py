"""The compiled matching kernel against its numpy twin and a plain loop (core._match_kernel)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core._match_kernel import _best_pair_numpy, _compiled, fixed_point_bits, quantise
from core.config import preset


def _loop_reference(templates, rows, view, offsets, width, start, limit_sum):  # type: ignore[no-untyped-def]
    """Every pair summed in Python integers; the first strict minimum within the limit wins."""
    best, where = None, (-1, -1, -1)
    for i, r in enumerate(rows.tolist()):
        for j, o in enumerate(offsets.tolist()):
            total = int(np.abs(view[:, start : start + width].astype(np.int64)
                               - templates[r, :, o : o + width].astype(np.int64)).sum())
            if total <= limit_sum and (best is None or total < best):
                best, where = total, (i, j, total)
    return where


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 12), ty=st.integers(1, 5), tx=st.integers(3, 14),
       limit=st.sampled_from([0, 5, 40, 10**12]), duplicates=st.booleans())  # fmt: skip
def test_kernel_numpy_and_loop_give_the_same_pair(seed: int, n: int, ty: int, tx: int, limit: int,
                                                  duplicates: bool) -> None:  # fmt: skip
    rng = np.random.default_rng(seed)
    templates = rng.integers(0, 6, (n, ty, tx)).astype(np.int32)  # small values: many exact ties
    if duplicates:
        templates[n // 2 :] = templates[0]
    shift = (tx - 1) // 2 if tx > 2 else 0
    shift = min(shift, 2)
    width = tx - 2 * shift
    offsets = np.arange(0, 2 * shift + 1)
    rows = np.sort(rng.choice(n, size=rng.integers(1, n + 1), replace=False)).astype(np.int64)
    view = templates[int(rng.integers(n))].copy()
    view += rng.integers(-1, 2, view.shape).astype(np.int32)
    want = _loop_reference(templates, rows, view, offsets, width, shift, limit)
    assert _best_pair_numpy(templates, rows, view, offsets, width, shift, limit) == want
    assert tuple(int(v) for v in _compiled()(templates, rows, view, offsets, width, shift, limit)) == want


def test_fixed_point_keeps_float32_precision_and_fits_int32_rows() -> None:
    assert fixed_point_bits(60, 1.0) == 24  # 60 columns of differences ≤ 1: 60·2^25 < 2^31
    assert fixed_point_bits(200, 1.0) == 22
    assert fixed_point_bits(60, 8.0) == 21  # values up to 8 (not from our templates): fewer bits
    values = np.array([0.0, 1.0, 0.5, 2.0**-24, 0.123456789], dtype=np.float32)
    q = quantise(values, 24)
    assert q.tolist()[:4] == [0, 2**24, 2**23, 1]
    assert abs(q[4] / 2**24 - float(values[4])) <= 2.0**-25
    worst = 2**24 * 60 * 2  # |difference| ≤ 2^24 per value over 60 columns twice over: still int32
    assert worst < 2**31


def test_loading_the_kernel_early_gives_it_the_types_the_matcher_calls_it_with(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``load_compiled`` (called before a run's clock) loads the one signature the matcher then uses: its calls,
    over a real template store and a prefiltered candidate list, compile nothing more (each new signature is a
    compile or cache load, ~0.3 s, that would fall inside the clock)."""
    from core import _match_kernel
    from core.localview import LocalViewCells, load_compiled

    load_compiled()
    loaded = list(_compiled().signatures)
    assert len(loaded) >= 1
    monkeypatch.setattr(_match_kernel, "_use_compiled", True)  # the compiled path from the first frame
    params = preset("circle")
    cells = LocalViewCells(params)
    rng = np.random.default_rng(4)
    images = rng.integers(0, 255, (6, 120, 160), dtype=np.uint8)
    for image in images:
        cells.process(image)
    template, mean = cells.make_template(images[2] // 2 + 40)
    answers = cells.match(template, mean), cells.match_among(template, mean, np.arange(cells.count))
    assert cells.count >= 2 and answers[0] == answers[1]
    assert list(_compiled().signatures) == loaded
    monkeypatch.setattr(_match_kernel, "_use_compiled", False)  # numpy's sums: the same answer
    assert cells.match(template, mean) == answers[0]


def _float64_reference(values: np.ndarray, bits: int) -> np.ndarray:
    return np.rint(values.astype(np.float64) * 2.0**bits).astype(np.int32)


@settings(max_examples=200, deadline=None)
@given(bits=st.integers(0, 24), data=st.data())
def test_float32_values_are_quantised_in_float32_to_the_float64_integers(bits: int, data: st.DataObject) -> None:
    """Any float32 whose fixed point fits int32 (subnormals, halves, negatives included) gives the integer that
    float64 arithmetic gives: scaling by 2^bits and rounding to an integer are exact in float32 too."""
    bound = float(np.float32(2.0 ** (30 - bits)))
    values = np.array(data.draw(st.lists(st.floats(-bound, bound, width=32), min_size=1, max_size=50)), np.float32)
    np.testing.assert_array_equal(quantise(values, bits), _float64_reference(values, bits))


def test_quantise_rounds_halves_to_even_without_a_float64_copy() -> None:
    import tracemalloc

    ulp = 2.0**-24
    halves = np.array([0.5 * ulp, 1.5 * ulp, 2.5 * ulp, -2.5 * ulp, 1e-45, 1.0 - ulp / 2], dtype=np.float32)
    assert quantise(halves, 24).tolist() == [0, 2, 2, -2, 0, 2**24]  # 1 − 2^-25 is float32: 2^24 − 0.5 → even
    values = np.random.default_rng(3).random(2**20, dtype=np.float32)  # 4 MB
    tracemalloc.start()
    try:
        fixed = quantise(values, 24)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 * 2**20 + 2**16  # a float32 temporary and the int32 result; a float64 copy alone is 8 MB
    np.testing.assert_array_equal(fixed, _float64_reference(values, 24))

"""The compiled inner loop of view matching: the best (template, offset) pair by summed absolute difference.

OpenRatSLAM's ``LocalViewMatch::compare`` visits every template and column offset, sums the absolute
differences between the view and the template's window row by row, and breaks off a sum as soon as it
exceeds the best found so far. That early break is what makes it fast on a large map (most pairs are
rejected after a few rows), and it is a per-pair branch that numpy cannot express: the vectorised
version had to compute every pair in full or bound them first. This kernel is the loop itself, compiled
by numba (``cache=True``: compiled once per machine, then loaded from ``__pycache__``).

Arithmetic: the templates and the view are compared in fixed point, ``round(value · 2^bits)`` as int32
(:func:`quantise`; ``bits`` = 24 for templates in [0, 1] up to 127 columns wide, so one row's sum fits
in int32 and a pair's in int64). Integer sums are exact whatever their order, so the compiler may
vectorise the row sums (measured: 4× the float64 loop) and the answer does not depend on the CPU.
Against float64 arithmetic on the stored float32 values the sum moves by at most one unit (2⁻²⁴)
per value. The visit order (templates by id, then offsets) and strict comparisons give OpenRatSLAM's
tie rule: the first minimum wins.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np

from core.arrays import Float32Array, Int32Array, IntArray

MAX_BITS = 24
"""Fixed-point bits when the values allow it (float32's precision at 1.0)."""
COMPILED_FROM = 100_000
"""Element operations of one frame's comparison from which the compiled kernel is used (:func:`best_pair`)."""
_use_compiled = False


def fixed_point_bits(width: int, peak: float) -> int:
    """Return the fixed-point bits for rows of ``width`` values of magnitude ≤ ``peak``: a row's sum fits in int32."""
    span = 2.0 * max(peak, 0.5) * max(width, 1)  # the largest row sum of |differences|, in value units
    return max(0, min(MAX_BITS, math.floor(math.log2((2**31 - 1) / span))))


def quantise(values: Float32Array, bits: int) -> Int32Array:
    """Return ``round(values · 2^bits)`` (half to even) as int32 (the kernel's fixed point).

    float32 values are scaled and rounded in float32, anything else in float64: the same integers either
    way (multiplying by a power of two is exact, and so is rounding a float to an integer), with one
    temporary of the input's size and type.
    """
    values = np.asarray(values)
    work = np.float32 if values.dtype == np.float32 else np.float64
    scaled = np.empty(values.shape, dtype=work)
    np.multiply(values, work(2**bits), out=scaled, dtype=work)
    return np.rint(scaled, out=scaled).astype(np.int32)


def best_pair(
    templates: Int32Array,
    rows: IntArray,
    view: Int32Array,
    offsets: IntArray,
    width: int,
    start: int,
    limit_sum: int,
) -> tuple[int, int, int]:
    """Return :func:`_best_pair`'s answer: compiled on large problems, numpy on small ones (the same integers).

    numba is imported, and the kernel loaded, on the first frame whose comparison would take numpy more than
    ``COMPILED_FROM`` element operations (≈ 0.1 ms); tiny maps (tests, the first frames) never pay for it (≈ 0.5 s).
    """
    global _use_compiled
    if not _use_compiled and rows.size * offsets.size * view.shape[0] * width >= COMPILED_FROM:
        _use_compiled = True
    if _use_compiled:
        return _compiled()(templates, rows, view, offsets, width, start, limit_sum)
    return _best_pair_numpy(templates, rows, view, offsets, width, start, limit_sum)


def _best_pair_numpy(
    templates: Int32Array,
    rows: IntArray,
    view: Int32Array,
    offsets: IntArray,
    width: int,
    start: int,
    limit_sum: int,
) -> tuple[int, int, int]:
    """Every pair's sum in full (exact integers: the same sums as the kernel), then the first minimum."""
    windows = np.lib.stride_tricks.sliding_window_view(templates[rows], width, axis=2)[:, :, offsets, :]
    seen = view[None, :, None, start : start + width]
    totals = np.abs(windows - seen).sum(axis=(1, 3), dtype=np.int64)  # (rows, offsets)
    flat = int(np.argmin(totals))
    if int(totals.flat[flat]) > limit_sum:
        return -1, -1, -1
    row, col = divmod(flat, offsets.size)
    return row, col, int(totals.flat[flat])


def load_compiled() -> None:
    """Import numba and load the kernel's machine code for the matcher's argument types, now.

    On first use that costs ~0.45 s here (numba's import 0.16 s, loading the cached code and numba's target
    registries 0.27 s), which a run paid inside its clock on its first large comparison: a caller that times
    frames (``mapserver process``) calls this before it starts the clock. Which frames use the kernel is
    unchanged (:func:`best_pair`), and so are its answers.
    """
    kernel = _compiled()
    templates = np.zeros((1, 1, 1), dtype=np.int32)  # the matcher's types: int32 fixed point, int64 ids and offsets
    kernel(templates, np.zeros(1, dtype=np.int64), templates[0], np.zeros(1, dtype=np.int64), 1, 0, 0)


@functools.cache
def _compiled() -> Callable[..., tuple[int, int, int]]:
    from numba import njit

    return njit(cache=True, nogil=True)(_best_pair)


def _best_pair(
    templates: Int32Array,
    rows: IntArray,
    view: Int32Array,
    offsets: IntArray,
    width: int,
    start: int,
    limit_sum: int,
) -> tuple[int, int, int]:
    """Return (index into ``rows``, index into ``offsets``, summed |difference|) of the best pair, or (−1, −1, −1).

    Args:
        templates: (N, ty, span) int32, the stored templates in fixed point (panoramic ones with their
            first ``width − 1`` columns repeated after the last, so every window is contiguous).
        rows: sorted template ids to compare (the prefiltered candidates).
        view: (ty, tx) int32, the current view's template in the same fixed point.
        offsets: column offsets into the template (ascending); window ``[offset, offset + width)``.
        width: compared columns; the view's are ``[start, start + width)``.
        start: the first compared view column.
        limit_sum: only sums ≤ this count.
    """
    ty = view.shape[0]
    n_off = offsets.size
    best = limit_sum
    best_row = -1
    best_col = -1
    total = np.zeros(n_off, np.int64)
    alive = np.zeros(n_off, np.bool_)
    for i in range(rows.size):
        template = templates[rows[i]]
        total[:] = 0
        alive[:] = True
        left = n_off
        for y in range(ty):  # row by row, every offset still alive: OpenRatSLAM's early break per pair
            seen = view[y, start : start + width]
            for j in range(n_off):
                if not alive[j]:
                    continue
                stored = template[y, offsets[j] : offsets[j] + width]
                row = np.int32(0)
                for x in range(width):
                    row += abs(seen[x] - stored[x])
                total[j] += row
                # a later pair wins only with a strictly smaller sum; the first one may equal the limit
                if total[j] > best or (best_row >= 0 and total[j] == best):
                    alive[j] = False
                    left -= 1
            if left == 0:
                break
        for j in range(n_off):
            if alive[j] and (total[j] < best or (best_row < 0 and total[j] <= best)):
                best = total[j]
                best_row = i
                best_col = j
    if best_row < 0:
        return -1, -1, -1
    return best_row, best_col, best

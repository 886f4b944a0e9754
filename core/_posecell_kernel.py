"""The compiled pose-cell update: attractor step, path integration and peak search, cell by cell.

:mod:`core.posecells` computes each frame's ``on_odo`` with whole-lattice numpy operations (its reference
path). These functions compute the same numbers where the packet is, as OpenRatSLAM visits only active cells:
the attractor step on a dense window of the lattice (per axis the shortest cyclic run of slices that covers the
active ones widened by the kernels' reach), path integration and the peak search on the occupied slices. They
are compiled by numba (``cache=True``: compiled once per machine, then loaded from ``__pycache__``; ``nogil``:
a reader thread runs meanwhile).

Arithmetic: every cell is computed by the same sequence of IEEE operations as the reference path, so the
two agree to the last bit (tests/core/test_posecell_kernel.py checks it on random packets):

* a spread along one axis (Menezes et al. 2023 Eq. 3, one separable factor of the excitatory or inhibitory
  Gaussian) is ``Σ_k w_k · P[i − o_k]`` accumulated from 0.0 in the order of the taps ``o_k``; taps whose
  source slice is empty add an exact 0.0 and are skipped;
* global inhibition and normalisation (Eq. 3): ``max(E − I − φ, 0)``, summed in C order from 0.0, each cell
  then divided by the sum;
* path integration: per heading layer ``keep_x·P[x−w_x] + frac_x·P[x−w_x−1]`` along x, then the same along y
  (PoseidonSLAM Eq. 4.17's translation), then z and θ as ``P[i−w]·keep + P[i−w−1]·frac``;
* the peak is the first maximum in the scan order of :meth:`core.posecells.PoseCellNetwork.decode`.

No fused multiply-adds: numba does not contract ``a·b + c`` without ``fastmath`` (the default here).

Layout: the lattice ``(x, y, [z,] θ)`` is passed as a 2-D C-contiguous ``(rows, n_θ)`` view, row
``(x·n_y + y)·n_z + z`` (``n_z = 1`` on the 3-DoF lattice, whose z pass is skipped), one of the network's
reused slots ``pool[slot]``; ``dirty[slot, row]`` marks the rows of a slot that may be non-zero, so a slot is
cleared by zeroing those rows alone. ``masks[a, i]`` (a = 0, 1, 2 for x, y, z; 3 for θ) says whether slice i
of axis a may hold activity; a set of rows is the product of three such masks.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from core.arrays import BoolArray, FloatArray, IntArray

_use_compiled = False


def enabled() -> bool:
    """Return whether :func:`load_compiled` has run: the pose cells then take the compiled path."""
    return _use_compiled


def load_compiled() -> None:
    """Import numba and load (compiling on first use on this machine) the kernels; the pose cells then use them.

    The results do not depend on which path runs (see the module docstring), so a network may switch at any
    frame: :class:`core.posecells.PoseCellNetwork` switches after ``COMPILED_AFTER`` cell updates, and
    ``mapserver process`` loads the kernels before its clock starts when the log is long.
    """
    global _use_compiled
    _compiled()
    _use_compiled = True


def kernel(name: str) -> Callable[..., Any]:
    """Return the compiled version of one of this module's kernels (``attractor``, ``path_integrate``, ``peak``)."""
    return _compiled()[name]


_ORDER = (
    "_rows", "_occupancy", "_clear", "_widen", "_window", "_lattice_order", "_add_scaled", "_pass_first",
    "_spread_block", "_block_window", "_gather", "_combine", "_restart",
    "attractor", "_layer_shift", "_translate", "_corner_loss", "_shift_outer", "_shift_heading", "path_integrate",
    "peak", "on_odo", "openratslam_axis_centre",
)  # fmt: skip


_COMPILE_LOCK = threading.Lock()
"""Held while the kernels are compiled: two jobs of a server may load them at once (each wraps the module's
functions in place, which must happen once)."""


@functools.cache
def _compiled() -> dict[str, Callable[..., Any]]:
    with _COMPILE_LOCK:
        return _compile_once()


@functools.cache
def _compile_once() -> dict[str, Callable[..., Any]]:
    from numba import njit

    module = globals()
    for name in _ORDER:  # callees first: a kernel calls the compiled versions of those above it
        module[name] = njit(cache=True, nogil=True)(module[name])
    return {name: module[name] for name in
            ("attractor", "path_integrate", "peak", "on_odo", "_occupancy", "openratslam_axis_centre")}  # fmt: skip


# ----------------------------------------------------------------------------------------------- helpers


def _rows(region: BoolArray, dims: IntArray, out: IntArray) -> int:
    """Write the rows of the product of ``region``'s x, y and z masks into ``out`` in C order; return their count."""
    ny, nz = dims[1], dims[2]
    count = 0
    for x in range(dims[0]):
        if region[0, x]:
            for y in range(ny):
                if region[1, y]:
                    for z in range(nz):
                        if region[2, z]:
                            out[count] = (x * ny + y) * nz + z
                            count += 1
    return count


def _occupancy(cells: FloatArray, dims: IntArray, masks: BoolArray, dirty: BoolArray) -> bool:
    """Set ``masks`` to the slices of every axis that hold a non-zero cell (exactly); return whether one is < 0.

    The rows holding one are marked in ``dirty`` (whatever wrote them).
    """
    masks[:, :] = False
    ny, nz = dims[1], dims[2]
    nt = cells.shape[1]
    negative = False
    for row in range(cells.shape[0]):
        seen = cells[row]
        hit = False
        for t in range(nt):
            hit |= seen[t] != 0.0
        if hit:
            for t in range(nt):
                if seen[t] != 0.0:
                    masks[3, t] = True
                    negative |= seen[t] < 0.0
            masks[0, row // (ny * nz)] = True
            masks[1, (row // nz) % ny] = True
            masks[2, row % nz] = True
            dirty[row] = True
    return negative


def _clear(cells: FloatArray, dirty: BoolArray) -> None:
    """Zero the rows of ``cells`` marked in ``dirty`` (every other row is 0 already) and unmark them."""
    for row in range(cells.shape[0]):
        if dirty[row]:
            cells[row, :] = 0.0
            dirty[row] = False


def _widen(mask: BoolArray, dim: int, offsets: IntArray, count: int) -> None:
    """Add to ``mask`` the slices ``(i + o) mod dim`` a spread's taps reach from its slices i."""
    old = mask[:dim].copy()
    for i in range(dim):
        if old[i]:
            for k in range(count):
                mask[(i + offsets[k]) % dim] = True


def _window(mask: BoolArray, dim: int, out: IntArray) -> None:
    """Set ``out`` to (start, length) of the shortest cyclic run of slices that covers ``mask``'s.

    The whole axis (no empty slice) is (0, dim); an empty mask (0, 0).
    """
    gap = 0
    gap_end = 0
    run = 0
    for i in range(2 * dim):
        if mask[i % dim]:
            run = 0
        else:
            run += 1
            if gap < run <= dim:
                gap, gap_end = run, i + 1
    out[0] = 0 if gap in (0, dim) else gap_end % dim
    out[1] = dim - gap


def _lattice_order(start: int, length: int, dim: int) -> IntArray:
    """Return the window's block indices in the order of their lattice slices, ascending."""
    order = np.empty(length, np.int64)
    n = 0
    for x in range(dim):
        i = (x - start) % dim
        if i < length:
            order[n] = i
            n += 1
    return order


def _add_scaled(out: FloatArray, w: float, seen: FloatArray) -> None:
    """``out[t] += w·seen[t]`` for every t (one tap of a spread on one contiguous run)."""
    for t in range(out.size):
        out[t] += w * seen[t]


def _pass_first(src: FloatArray, dst: FloatArray, signed: IntArray, weights: FloatArray, cyclic: bool) -> None:
    """Spread along the first axis of (L, B) arrays: ``dst[i] = Σ_k w_k·src[i − o_k]``, taps in order.

    Sources outside [0, L) are zeros (skipped) unless ``cyclic`` (the window is the whole axis: they wrap).
    """
    length, width = src.shape
    flat_out = dst.reshape(length * width)
    flat_in = src.reshape(length * width)
    flat_out[:] = 0.0
    for k in range(weights.size):
        o, w = signed[k], weights[k]
        lo, hi = max(0, o), min(length, length + o)
        if lo < hi:
            _add_scaled(flat_out[lo * width : hi * width], w, flat_in[(lo - o) * width : (hi - o) * width])
        if cyclic and o > 0:
            _add_scaled(flat_out[: o * width], w, flat_in[(length - o) * width :])
        elif cyclic and o < 0:
            _add_scaled(flat_out[(length + o) * width :], w, flat_in[: -o * width])


def _spread_block(
    block: FloatArray, lengths: IntArray, cyclic: BoolArray, signed: IntArray, weights: FloatArray,
    counts: IntArray,
) -> FloatArray:  # fmt: skip
    """Return one separable kernel applied to ``block`` (a window, (L_x, L_y, L_z, L_θ)) along x, y, [z] then θ."""
    lx, ly, lz, lt = block.shape
    src = block
    for axis in range(3):
        if counts[axis] == 0:
            continue
        outer = 1 if axis == 0 else (lx if axis == 1 else lx * ly)
        inner = (ly * lz * lt) if axis == 0 else (lz * lt if axis == 1 else lt)
        dst = np.empty_like(src)
        s3 = src.reshape((outer, lengths[axis], inner))
        d3 = dst.reshape((outer, lengths[axis], inner))
        for a in range(outer):
            _pass_first(s3[a], d3[a], signed[axis, : counts[axis]], weights[axis, : counts[axis]], cyclic[axis])
        src = dst
    heading = np.ascontiguousarray(src.reshape((lx * ly * lz, lt)).T)  # θ first: every tap one run
    turned = np.empty_like(heading)
    _pass_first(heading, turned, signed[3, : counts[3]], weights[3, : counts[3]], cyclic[3])
    return np.ascontiguousarray(turned.T).reshape((lx, ly, lz, lt))


def _block_window(
    masks: BoolArray, dims: IntArray, signed: IntArray, counts: IntArray, windows: IntArray
) -> None:
    """Set ``windows`` (4, 2) to the (start, length) of x, y, z, θ covering ``masks`` widened by the taps ``signed``."""
    for axis in range(4):
        if counts[axis] > 0:
            _widen(masks[axis], dims[axis], signed[axis], counts[axis])
        _window(masks[axis], dims[axis], windows[axis])


def _gather(cells: FloatArray, dims: IntArray, windows: IntArray) -> FloatArray:
    """Return the window of ``cells`` as a (L_x, L_y, L_z, L_θ) block."""
    ny, nz, nt = dims[1], dims[2], dims[3]
    block = np.empty((windows[0, 1], windows[1, 1], windows[2, 1], windows[3, 1]))
    thetas = (windows[3, 0] + np.arange(windows[3, 1])) % nt
    for i in range(windows[0, 1]):
        x = (windows[0, 0] + i) % dims[0]
        for j in range(windows[1, 1]):
            y = (windows[1, 0] + j) % ny
            for m in range(windows[2, 1]):
                row = cells[(x * ny + y) * nz + (windows[2, 0] + m) % nz]
                out = block[i, j, m]
                for q in range(thetas.size):
                    out[q] = row[thetas[q]]
    return block


def _combine(
    excited: FloatArray, inhibited: FloatArray, out: FloatArray, dirty: BoolArray, dims: IntArray,
    windows: IntArray, inhibition: float, masks: BoolArray,
) -> float:  # fmt: skip
    """Write ``max(E − I − φ, 0)`` of the window into ``out`` (0 elsewhere); return the sum in lattice C order.

    Off the window E = 0 and I ≥ 0 (the caller's window), so the value there is 0 too. ``masks`` receives the
    result's slices, ``dirty`` (``out``'s non-zero rows) the rows written.
    """
    _clear(out, dirty)
    masks[:, :] = False
    ny, nz, nt = dims[1], dims[2], dims[3]
    thetas = _lattice_order(windows[3, 0], windows[3, 1], nt)
    total = 0.0
    for i in _lattice_order(windows[0, 0], windows[0, 1], dims[0]):
        x = (windows[0, 0] + i) % dims[0]
        for j in _lattice_order(windows[1, 0], windows[1, 1], ny):
            y = (windows[1, 0] + j) % ny
            for m in _lattice_order(windows[2, 0], windows[2, 1], nz):
                z = (windows[2, 0] + m) % nz
                e, inh, cells = excited[i, j, m], inhibited[i, j, m], out[(x * ny + y) * nz + z]
                hit = False
                for q in thetas:
                    value = e[q] - inh[q]
                    value = value - inhibition
                    if value < 0.0:
                        value = 0.0
                    t = (windows[3, 0] + q) % nt
                    cells[t] = value
                    total += value
                    if value != 0.0:
                        masks[3, t] = True
                        hit = True
                if hit:
                    masks[0, x] = masks[1, y] = masks[2, z] = True
                    dirty[(x * ny + y) * nz + z] = True
    return total


# ------------------------------------------------------------------------------------------------ kernels


def attractor(
    pool: FloatArray, dirty: BoolArray, source: int, dims: IntArray, masks: BoolArray,
    e_signed: IntArray, e_weights: FloatArray, e_counts: IntArray,
    i_signed: IntArray, i_weights: FloatArray, i_counts: IntArray, inhibition: float, best: FloatArray,
) -> tuple[int, float]:  # fmt: skip
    """One attractor step of ``pool[source]`` (Menezes et al. Eq. 3); return (the result's slot, the pre-scale sum).

    Excitation E, inhibition I of E, then ``max(E − I − φ, 0)`` normalised to sum 1 when the sum is positive;
    otherwise (everything inhibited) one cell at the decoded centre ``best`` (truncated) holds 1. The work is
    done on a dense window of the lattice: per axis the shortest cyclic run of slices covering the active ones
    widened by the excitation's reach (and by the inhibition's when a cell is negative, as
    ``openratslam_compat``'s translation can leave: I then matters beyond E). ``masks`` (4, 4, width) is
    scratch; on return ``masks[0]`` holds the result's slices. Slot ``source`` is kept; another is written.
    ``dirty[slot]`` marks the rows of each slot that may be non-zero (a slot's other rows are 0).
    """
    region = masks[1]
    negative = _occupancy(pool[source], dims, region, dirty[source])
    windows = np.zeros((4, 2), np.int64)
    sizes = np.array([dims[0], dims[1], dims[2], pool.shape[2]])  # x, y, z, θ
    _block_window(region, sizes, e_signed, e_counts, windows)
    if negative:
        _block_window(region, sizes, i_signed, i_counts, windows)
    if inhibition < 0.0:  # never (the parameters forbid it): every cell would be positive
        windows[:, 0] = 0
        windows[:, 1] = sizes
    cyclic = windows[:, 1] == sizes
    block = _gather(pool[source], sizes, windows)
    excited = _spread_block(block, windows[:, 1], cyclic, e_signed, e_weights, e_counts)
    inhibited = _spread_block(excited, windows[:, 1], cyclic, i_signed, i_weights, i_counts)
    out = 0 if source != 0 else 1
    cells = pool[out]
    total = _combine(excited, inhibited, cells, dirty[out], sizes, windows, inhibition, masks[0])
    if total > 0.0:
        for row in range(cells.shape[0]):
            if dirty[out, row]:  # every other row is 0 and stays 0
                cells[row] /= total
    else:
        _restart(cells, dirty[out], dims, masks[0], best)
    return out, total


def _restart(cells: FloatArray, dirty: BoolArray, dims: IntArray, masks: BoolArray, best: FloatArray) -> None:
    """Set ``cells`` to one cell of 1 at ``best`` truncated to integers (x, y, [z,] θ), ``masks`` to its slices."""
    _clear(cells, dirty)
    masks[:, :] = False
    nt = cells.shape[1]
    at = np.empty(4, np.int64)
    for a in range(best.size):
        d = dims[a] if a < best.size - 1 else nt
        at[a if a < best.size - 1 else 3] = int(best[a]) % d
    if best.size == 3:
        at[2] = 0
    row = (at[0] * dims[1] + at[1]) * dims[2] + at[2]
    cells[row, at[3]] = 1.0
    dirty[row] = True
    for a in range(4):
        masks[a, at[a]] = True


def _layer_shift(shift: float, one_cell: bool) -> tuple[int, float, float]:
    """Return (whole, keep, frac) of a move by ``shift`` cells: ⌊s⌋ (0 or −1 with ``one_cell``), 1 − frac, s − whole."""
    whole = (0.0 if shift >= 0.0 else -1.0) if one_cell else float(math.floor(shift))
    frac = shift - whole
    return int(whole), 1.0 - frac, frac


def _translate(
    src: FloatArray, dst: FloatArray, dirty: BoolArray, dims: IntArray, masks: BoolArray, v: float,
    cos: FloatArray, sin: FloatArray, one_cell: bool, moved: BoolArray,
) -> None:  # fmt: skip
    """Move every heading layer t by ``v`` cells along (cos_t, sin_t) within its (x, y) plane: x then y, wrapping.

    Cell i receives ``keep·P[i − whole] + frac·P[i − whole − 1]`` along each axis (:func:`_layer_shift`).
    ``masks`` are ``src``'s slices, ``moved`` receives ``dst``'s (rows written), ``dirty`` (``dst``'s non-zero
    rows) the rows written.
    """
    _clear(dst, dirty)
    moved[:, :] = False
    nx, ny, nz = dims[0], dims[1], dims[2]
    for t in range(dst.shape[1]):
        if not masks[3, t]:
            continue
        wx, kx, fx = _layer_shift(v * cos[t], one_cell)
        wy, ky, fy = _layer_shift(v * sin[t], one_cell)
        moved[3, t] = True
        for x in range(nx):
            x1, x2 = (x - wx) % nx, (x - wx - 1) % nx
            if not (masks[0, x1] or masks[0, x2]):
                continue
            for y in range(ny):
                y1, y2 = (y - wy) % ny, (y - wy - 1) % ny
                if not (masks[1, y1] or masks[1, y2]):
                    continue
                moved[0, x] = True
                moved[1, y] = True
                for z in range(nz):
                    if masks[2, z]:
                        a = kx * src[(x1 * ny + y1) * nz + z, t] + fx * src[(x2 * ny + y1) * nz + z, t]
                        b = kx * src[(x1 * ny + y2) * nz + z, t] + fx * src[(x2 * ny + y2) * nz + z, t]
                        dst[(x * ny + y) * nz + z, t] = ky * a + fy * b
                        dirty[(x * ny + y) * nz + z] = True
    moved[2, :] = masks[2]


def _corner_loss(src: FloatArray, dst: FloatArray, dirty: BoolArray, masks: BoolArray, corners: FloatArray) -> None:
    """OpenRatSLAM's translation loss (``openratslam_compat``): ``dst[to] −= src[a]·w_a + src[b]·w_b`` per layer.

    ``corners[t]`` = (row a, w_a, row b, w_b, row to) of layer t (3-DoF lattice).
    """
    for t in range(dst.shape[1]):
        if masks[3, t]:
            lost = src[int(corners[t, 0]), t] * corners[t, 1] + src[int(corners[t, 2]), t] * corners[t, 3]
            if lost != 0.0:
                dst[int(corners[t, 4]), t] -= lost
                dirty[int(corners[t, 4])] = True


def _shift_outer(
    src: FloatArray, dst: FloatArray, dirty: BoolArray, dims: IntArray, masks: BoolArray, whole: int,
    keep: float, frac: float,
) -> None:  # fmt: skip
    """Shift along z: ``dst[z] = src[z − whole]·keep + src[z − whole − 1]·frac`` (wrapping) on ``masks``' x, y rows."""
    _clear(dst, dirty)
    ny, nz = dims[1], dims[2]
    for x in range(dims[0]):
        if not masks[0, x]:
            continue
        for y in range(ny):
            if not masks[1, y]:
                continue
            base = (x * ny + y) * nz
            dirty[base : base + nz] = True
            for z in range(nz):
                a = src[base + (z - whole) % nz]
                if frac == 0.0:
                    dst[base + z, :] = a
                else:
                    b = src[base + (z - whole - 1) % nz]
                    for t in range(dst.shape[1]):
                        dst[base + z, t] = a[t] * keep + b[t] * frac
    masks[2, :] = True


def _shift_heading(
    src: FloatArray, dst: FloatArray, dirty: BoolArray, rows: IntArray, n_rows: int, whole: int, keep: float,
    frac: float,
) -> None:  # fmt: skip
    """Shift along θ on ``rows``: ``dst[t] = src[t − whole]·keep + src[t − whole − 1]·frac`` (wrapping)."""
    _clear(dst, dirty)
    nt = dst.shape[1]
    for n in range(n_rows):
        r = rows[n]
        dirty[r] = True
        for t in range(nt):
            a = src[r, (t - whole) % nt]
            if frac == 0.0:
                dst[r, t] = a
            else:
                dst[r, t] = a * keep + src[r, (t - whole - 1) % nt] * frac


def path_integrate(
    pool: FloatArray, dirty: BoolArray, source: int, dims: IntArray, masks: BoolArray, rows: IntArray,
    known: bool,
    v: float, cos: FloatArray, sin: FloatArray, one_cell: bool, corners: FloatArray, z_shift: FloatArray,
    th_shift: FloatArray,
) -> int:  # fmt: skip
    """Translate by ``v`` cells (when ≠ 0), then shift z, then θ, ``pool[source]``; return the result's slot.

    ``known``: ``masks[0]`` already holds the source's slices (else they are scanned). ``corners`` (rows per
    layer, see :func:`_corner_loss`) applies when it has rows. ``z_shift`` and ``th_shift`` = (apply, whole,
    keep, frac). The result's slot is ``source`` when nothing moves. On return ``masks[0]`` holds slices that
    cover the result's.
    """
    if not known:
        _occupancy(pool[source], dims, masks[0], dirty[source])
    slot = source
    free = 0 if source != 0 else 1
    spare = 2 if source != 2 else 1
    if free == spare:
        spare = 3
    if v != 0.0:
        _translate(pool[slot], pool[free], dirty[free], dims, masks[0], v, cos, sin, one_cell, masks[1])
        if corners.shape[0] > 0:
            _corner_loss(pool[slot], pool[free], dirty[free], masks[0], corners)
        masks[0, :, :] = masks[1]
        slot, free = free, (spare if slot == source else slot)
    if z_shift[0] != 0.0:
        _shift_outer(pool[slot], pool[free], dirty[free], dims, masks[0], int(z_shift[1]), z_shift[2], z_shift[3])
        slot, free = free, (spare if slot == source else slot)
    if th_shift[0] != 0.0:
        n_rows = _rows(masks[0], dims, rows)
        _shift_heading(pool[slot], pool[free], dirty[free], rows, n_rows, int(th_shift[1]), th_shift[2],
                       th_shift[3])
        masks[0, 3, :] = True
        slot = free
    return slot


def on_odo(
    pool: FloatArray, dirty: BoolArray, source: int, dims: IntArray, masks: BoolArray, rows: IntArray,
    e_signed: IntArray, e_weights: FloatArray, e_counts: IntArray,
    i_signed: IntArray, i_weights: FloatArray, i_counts: IntArray, inhibition: float,
    best: FloatArray, v: float, cos: FloatArray, sin: FloatArray, one_cell: bool, corners: FloatArray,
    z_shift: FloatArray, th_shift: FloatArray, x_first: bool,
) -> tuple[int, IntArray]:  # fmt: skip
    """:func:`attractor`, :func:`path_integrate` and :func:`peak` in one call; return (the result's slot, its peak)."""
    slot, _ = attractor(pool, dirty, source, dims, masks, e_signed, e_weights, e_counts, i_signed, i_weights,
                        i_counts, inhibition, best)
    slot = path_integrate(pool, dirty, slot, dims, masks, rows, True, v, cos, sin, one_cell, corners, z_shift,
                          th_shift)
    return slot, peak(pool[slot], dims, masks[0], x_first)


def peak(cells: FloatArray, dims: IntArray, masks: BoolArray, x_first: bool) -> IntArray:
    """Return (x, y, z, θ) of the first maximum scanning θ outermost, then z, y, x (or x, y, z when ``x_first``).

    Only the slices in ``masks`` are visited (every other cell is 0); an all-zero lattice gives (0, 0, 0, 0).
    """
    ny, nz = dims[1], dims[2]
    xs = np.flatnonzero(masks[0, : dims[0]])
    ys = np.flatnonzero(masks[1, :ny])
    zs = np.flatnonzero(masks[2, :nz])
    outer, inner = (xs, zs) if x_first else (zs, xs)
    best = np.zeros(4, np.int64)
    top = 0.0
    for t in range(cells.shape[1]):
        if not masks[3, t]:
            continue
        for a in outer:
            for y in ys:
                for c in inner:
                    x, z = (a, c) if x_first else (c, a)
                    value = cells[(x * ny + y) * nz + z, t]
                    if value > top:
                        top = value
                        best[0], best[1], best[2], best[3] = x, y, z, t
    return best


def openratslam_axis_centre(flat: FloatArray, cells: IntArray, sines: FloatArray, cosines: FloatArray) -> float:
    """Return one axis of OpenRatSLAM's ``find_best`` centre, as :meth:`core.posecells.PoseCellNetwork` decodes it.

    ``flat`` is the packet's box with that axis last, the others in OpenRatSLAM's loop order, as (rows, n):
    each column is summed from 0.0 row by row (numpy's sum over axis 0, to the bit); ``cells`` are the axis'
    lattice indices of the n columns (distinct), visited in increasing index as OpenRatSLAM's loop does,
    adding ``sines[cell]·weight`` and ``cosines[cell]·weight``; then ``atan2(s, c)·dim/(2π) − 1`` wrapped into
    [0, dim] by whole turns.
    """
    rows, n = flat.shape
    marginal = np.zeros(n)
    for m in range(rows):
        for j in range(n):
            marginal[j] += flat[m, j]
    s = 0.0
    c = 0.0
    for k in np.argsort(cells):
        s += sines[cells[k]] * marginal[k]
        c += cosines[cells[k]] * marginal[k]
    dim = sines.size
    value = math.atan2(s, c) * dim / (2.0 * math.pi) - 1.0
    while value < 0.0:
        value += dim
    while value > dim:
        value -= dim
    return value

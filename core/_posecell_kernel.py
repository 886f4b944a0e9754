"""The compiled pose-cell update: attractor step, path integration and peak search, cell by cell.

:mod:`core.posecells` computes each frame's ``on_odo`` with whole-lattice numpy operations (its reference
path). These functions compute the same numbers with loops that visit only the slices holding activity, as
OpenRatSLAM visits only active cells, compiled by numba (``cache=True``: compiled once per machine, then
loaded from ``__pycache__``; ``nogil``: a reader thread runs meanwhile).

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
``(x·n_y + y)·n_z + z`` (``n_z = 1`` on the 3-DoF lattice, whose z pass is skipped). ``masks[a, i]`` (a = 0, 1,
2 for x, y, z; 3 for θ) says whether slice i of axis a may hold activity; a set of rows is the product of
three such masks.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any

import numpy as np

_use_compiled = False


def enabled() -> bool:
    """Return whether :func:`load_compiled` has run: the pose cells then take the compiled path."""
    return _use_compiled


def load_compiled() -> None:
    """Import numba and load (compiling on first use on this machine) the kernels; the pose cells then use them.

    The results do not depend on which path runs (see the module docstring), so a network may switch at any
    frame: :class:`core.posecells.PoseCellNetwork` switches after ``COMPILED_AFTER`` updates, and
    ``mapserver process`` loads the kernels before its clock starts when the log is long.
    """
    global _use_compiled
    _compiled()
    _use_compiled = True


def kernel(name: str) -> Callable[..., Any]:
    """Return the compiled version of one of this module's kernels (``attractor``, ``path_integrate``, ``peak``)."""
    return _compiled()[name]


_ORDER = (
    "_rows", "_occupancy", "_widen", "_segments", "_add_scaled", "_pass_outer", "_pass_heading", "_spread",
    "_combine", "_restart",
    "attractor", "_layer_shift", "_translate", "_corner_loss", "_shift_outer", "_shift_heading", "path_integrate",
    "peak", "on_odo",
)  # fmt: skip


@functools.cache
def _compiled() -> dict[str, Callable[..., Any]]:
    from numba import njit

    module = globals()
    for name in _ORDER:  # callees first: a kernel calls the compiled versions of those above it
        module[name] = njit(cache=True, nogil=True)(module[name])
    return {name: module[name] for name in ("attractor", "path_integrate", "peak", "on_odo", "_occupancy")}


# ----------------------------------------------------------------------------------------------- helpers


def _rows(region: np.ndarray, dims: np.ndarray, out: np.ndarray) -> int:
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


def _occupancy(cells: np.ndarray, dims: np.ndarray, masks: np.ndarray) -> bool:
    """Set ``masks`` to the slices of every axis that hold a non-zero cell (exactly); return whether one is < 0."""
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
    return negative


def _widen(mask: np.ndarray, dim: int, offsets: np.ndarray, count: int) -> None:
    """Add to ``mask`` the slices ``(i + o) mod dim`` a spread's taps reach from its slices i."""
    old = mask[:dim].copy()
    for i in range(dim):
        if old[i]:
            for k in range(count):
                mask[(i + offsets[k]) % dim] = True


def _segments(mask: np.ndarray, count: int, out: np.ndarray) -> int:
    """Write the runs of True in ``mask[:count]`` as [start, end) rows of ``out``; return how many."""
    n = 0
    t = 0
    while t < count:
        if mask[t]:
            out[n, 0] = t
            while t < count and mask[t]:
                t += 1
            out[n, 1] = t
            n += 1
        else:
            t += 1
    return n


def _add_scaled(out: np.ndarray, w: float, seen: np.ndarray) -> None:
    """``out[t] += w·seen[t]`` for every t (one tap of a spread on one contiguous run)."""
    for t in range(out.size):
        out[t] += w * seen[t]


def _pass_outer(
    src: np.ndarray, dst: np.ndarray, axis: int, dims: np.ndarray, rows: np.ndarray, n_rows: int,
    source: np.ndarray, segs: np.ndarray, n_segs: int, offsets: np.ndarray, weights: np.ndarray, count: int,
) -> None:  # fmt: skip
    """Spread along outer axis ``axis`` (x, y or z): ``dst[i] = Σ_k w_k·src[i − o_k]`` on ``rows``, θ in ``segs``.

    ``source`` is the axis's mask of ``src``: taps from other slices read zeros and are skipped. Every written
    row is 0 off the θ runs ``segs`` (the only layers ``src`` holds).
    """
    ny, nz = dims[1], dims[2]
    dim = dims[axis]
    stride = ny * nz if axis == 0 else (nz if axis == 1 else 1)
    for n in range(n_rows):
        r = rows[n]
        c = r // (ny * nz) if axis == 0 else ((r // nz) % ny if axis == 1 else r % nz)
        out = dst[r]
        out[:] = 0.0
        for k in range(count):
            j = (c - offsets[k]) % dim
            if source[j]:
                seen = src[r + (j - c) * stride]
                w = weights[k]
                for s in range(n_segs):
                    _add_scaled(out[segs[s, 0] : segs[s, 1]], w, seen[segs[s, 0] : segs[s, 1]])


def _pass_heading(
    src: np.ndarray, dst: np.ndarray, rows: np.ndarray, n_rows: int, segs: np.ndarray, n_segs: int,
    signed: np.ndarray, weights: np.ndarray,
) -> None:  # fmt: skip
    """Spread along θ on ``rows``: ``dst[r, t] = Σ_k w_k·src[r, (t − o_k) mod n_θ]`` for t in ``segs``, 0 elsewhere.

    ``signed`` holds the offsets o_k in (−n_θ/2, n_θ/2]; each row is read through a copy padded by wrapping, so
    every tap is a contiguous run.
    """
    nt = src.shape[1]
    pad = 0
    for k in range(weights.size):
        pad = max(pad, abs(signed[k]))
    ext = np.empty(nt + 2 * pad)
    for n in range(n_rows):
        r = rows[n]
        seen = src[r]
        for i in range(nt + 2 * pad):
            ext[i] = seen[(i - pad) % nt]
        out = dst[r]
        out[:] = 0.0
        for k in range(weights.size):
            w = weights[k]
            base = pad - signed[k]
            for s in range(n_segs):
                _add_scaled(out[segs[s, 0] : segs[s, 1]], w, ext[base + segs[s, 0] : base + segs[s, 1]])


def _spread(
    pool: np.ndarray, src: int, scratch: np.ndarray, dims: np.ndarray, region: np.ndarray, widen: bool,
    rows: np.ndarray, offsets: np.ndarray, weights: np.ndarray, counts: np.ndarray, signed: np.ndarray,
) -> int:  # fmt: skip
    """Spread ``pool[src]`` along x, y, [z] then θ by one separable kernel; return the result's slot.

    ``region`` holds the source's slices on entry and the result's on return: the slices the taps reach when
    ``widen``, else the source's own (the result is then needed there only). The passes alternate between
    ``scratch[0]`` and ``scratch[1]``; the θ pass writes ``scratch[2]``.
    """
    nt = pool.shape[2]
    segs = np.empty((nt, 2), np.int64)
    n_segs = _segments(region[3], nt, segs)
    flip = 0
    for axis in range(3):
        if counts[axis] == 0:
            continue
        source = region[axis].copy()
        if widen:
            _widen(region[axis], dims[axis], offsets[axis], counts[axis])
        n_rows = _rows(region, dims, rows)
        dst = scratch[flip]
        _pass_outer(pool[src], pool[dst], axis, dims, rows, n_rows, source, segs, n_segs, offsets[axis],
                    weights[axis], counts[axis])
        src, flip = dst, 1 - flip
    if widen:
        _widen(region[3], nt, offsets[3], counts[3])
    n_rows = _rows(region, dims, rows)
    n_segs = _segments(region[3], nt, segs)
    _pass_heading(pool[src], pool[scratch[2]], rows, n_rows, segs, n_segs, signed, weights[3, : counts[3]])
    return scratch[2]


def _combine(
    excited: np.ndarray, inhibited: np.ndarray, out: np.ndarray, dims: np.ndarray, spread: np.ndarray,
    rows: np.ndarray, n_rows: int, theta: np.ndarray, inhibition: float, masks: np.ndarray,
) -> float:  # fmt: skip
    """Write ``max(E − I − φ, 0)`` on ``rows`` and θ ``theta``, 0 elsewhere; return the sum in C order.

    E is 0 off ``spread``'s rows. Off ``rows`` and ``theta`` E = 0 and I ≥ 0 (the caller's choice), so the
    value there is 0 too. ``masks`` receives the result's slices.
    """
    out[:, :] = 0.0
    masks[:, :] = False
    ny, nz = dims[1], dims[2]
    total = 0.0
    for n in range(n_rows):
        r = rows[n]
        x, y, z = r // (ny * nz), (r // nz) % ny, r % nz
        inside = spread[0, x] and spread[1, y] and spread[2, z]
        hit = False
        for t in theta:
            value = (excited[r, t] if inside else 0.0) - inhibited[r, t]
            value = value - inhibition
            if value < 0.0:
                value = 0.0
            out[r, t] = value
            total += value
            if value != 0.0:
                masks[3, t] = True
                hit = True
        if hit:
            masks[0, x] = True
            masks[1, y] = True
            masks[2, z] = True
    return total


# ------------------------------------------------------------------------------------------------ kernels


def attractor(
    pool: np.ndarray, source: int, dims: np.ndarray, masks: np.ndarray, rows: np.ndarray,
    e_offsets: np.ndarray, e_weights: np.ndarray, e_counts: np.ndarray, e_signed: np.ndarray,
    i_offsets: np.ndarray, i_weights: np.ndarray, i_counts: np.ndarray, i_signed: np.ndarray, inhibition: float,
    best: np.ndarray,
) -> tuple[int, float]:  # fmt: skip
    """One attractor step of ``pool[source]`` (Menezes et al. Eq. 3); return (the result's slot, the pre-scale sum).

    Excitation E, inhibition I of E, then ``max(E − I − φ, 0)`` normalised to sum 1 when the sum is positive;
    otherwise (everything inhibited) one cell at the decoded centre ``best`` (truncated) holds 1. I is computed
    where E may be non-zero only (elsewhere ``0 − I − φ ≤ 0`` as I ≥ 0), or wherever it reaches when a cell is
    negative (``openratslam_compat``'s translation can leave some). ``masks`` (4, 4, width) is scratch; on
    return ``masks[0]`` holds the result's slices. ``pool`` has ≥ 5 slots; every slot but ``source`` is
    overwritten.
    """
    free = np.empty(4, np.int64)
    n = 0
    for slot in range(pool.shape[0]):
        if slot != source and n < 4:
            free[n] = slot
            n += 1
    region = masks[1]
    negative = _occupancy(pool[source], dims, region)
    excited = _spread(pool, source, free[:3], dims, region, True, rows, e_offsets, e_weights, e_counts, e_signed)
    masks[2, :, :] = region  # E's slices
    scratch = np.array([free[0], free[1], free[3]])
    inhibited = _spread(pool, excited, scratch, dims, region, negative, rows, i_offsets, i_weights, i_counts,
                        i_signed)
    n_rows = _rows(region, dims, rows)
    theta = np.flatnonzero(region[3, : pool.shape[2]])
    out = free[0]
    cells = pool[out]
    total = _combine(pool[excited], pool[inhibited], cells, dims, masks[2], rows, n_rows, theta, inhibition,
                     masks[0])
    if total > 0.0:
        for m in range(n_rows):
            r = rows[m]
            for t in theta:
                cells[r, t] = cells[r, t] / total
    else:
        _restart(cells, dims, masks[0], best)
    return out, total


def _restart(cells: np.ndarray, dims: np.ndarray, masks: np.ndarray, best: np.ndarray) -> None:
    """Set ``cells`` to one cell of 1 at ``best`` truncated to integers (x, y, [z,] θ), ``masks`` to its slices."""
    cells[:, :] = 0.0
    masks[:, :] = False
    nt = cells.shape[1]
    at = np.empty(4, np.int64)
    for a in range(best.size):
        d = dims[a] if a < best.size - 1 else nt
        at[a if a < best.size - 1 else 3] = int(best[a]) % d
    if best.size == 3:
        at[2] = 0
    cells[(at[0] * dims[1] + at[1]) * dims[2] + at[2], at[3]] = 1.0
    for a in range(4):
        masks[a, at[a]] = True


def _layer_shift(shift: float, one_cell: bool) -> tuple[int, float, float]:
    """Return (whole, keep, frac) of a move by ``shift`` cells: ⌊s⌋ (0 or −1 with ``one_cell``), 1 − frac, s − whole."""
    whole = (0.0 if shift >= 0.0 else -1.0) if one_cell else float(math.floor(shift))
    frac = shift - whole
    return int(whole), 1.0 - frac, frac


def _translate(
    src: np.ndarray, dst: np.ndarray, dims: np.ndarray, masks: np.ndarray, v: float, cos: np.ndarray,
    sin: np.ndarray, one_cell: bool, moved: np.ndarray,
) -> None:  # fmt: skip
    """Move every heading layer t by ``v`` cells along (cos_t, sin_t) within its (x, y) plane: x then y, wrapping.

    Cell i receives ``keep·P[i − whole] + frac·P[i − whole − 1]`` along each axis (:func:`_layer_shift`).
    ``masks`` are ``src``'s slices, ``moved`` receives ``dst``'s (rows written).
    """
    dst[:, :] = 0.0
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
    moved[2, :] = masks[2]


def _corner_loss(src: np.ndarray, dst: np.ndarray, masks: np.ndarray, corners: np.ndarray) -> None:
    """OpenRatSLAM's translation loss (``openratslam_compat``): ``dst[to] −= src[a]·w_a + src[b]·w_b`` per layer.

    ``corners[t]`` = (row a, w_a, row b, w_b, row to) of layer t (3-DoF lattice).
    """
    for t in range(dst.shape[1]):
        if masks[3, t]:
            lost = src[int(corners[t, 0]), t] * corners[t, 1] + src[int(corners[t, 2]), t] * corners[t, 3]
            if lost != 0.0:
                dst[int(corners[t, 4]), t] -= lost


def _shift_outer(
    src: np.ndarray, dst: np.ndarray, dims: np.ndarray, masks: np.ndarray, whole: int, keep: float, frac: float
) -> None:
    """Shift along z: ``dst[z] = src[z − whole]·keep + src[z − whole − 1]·frac`` (wrapping) on ``masks``' x, y rows."""
    dst[:, :] = 0.0
    ny, nz = dims[1], dims[2]
    for x in range(dims[0]):
        if not masks[0, x]:
            continue
        for y in range(ny):
            if not masks[1, y]:
                continue
            base = (x * ny + y) * nz
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
    src: np.ndarray, dst: np.ndarray, rows: np.ndarray, n_rows: int, whole: int, keep: float, frac: float
) -> None:
    """Shift along θ on ``rows``: ``dst[t] = src[t − whole]·keep + src[t − whole − 1]·frac`` (wrapping)."""
    dst[:, :] = 0.0
    nt = dst.shape[1]
    for n in range(n_rows):
        r = rows[n]
        for t in range(nt):
            a = src[r, (t - whole) % nt]
            if frac == 0.0:
                dst[r, t] = a
            else:
                dst[r, t] = a * keep + src[r, (t - whole - 1) % nt] * frac


def path_integrate(
    pool: np.ndarray, source: int, dims: np.ndarray, masks: np.ndarray, rows: np.ndarray, known: bool,
    v: float, cos: np.ndarray, sin: np.ndarray, one_cell: bool, corners: np.ndarray, z_shift: np.ndarray,
    th_shift: np.ndarray,
) -> int:  # fmt: skip
    """Translate by ``v`` cells (when ≠ 0), then shift z, then θ, ``pool[source]``; return the result's slot.

    ``known``: ``masks[0]`` already holds the source's slices (else they are scanned). ``corners`` (rows per
    layer, see :func:`_corner_loss`) applies when it has rows. ``z_shift`` and ``th_shift`` = (apply, whole,
    keep, frac). The result's slot is ``source`` when nothing moves. On return ``masks[0]`` holds slices that
    cover the result's.
    """
    if not known:
        _occupancy(pool[source], dims, masks[0])
    slot = source
    free = 0 if source != 0 else 1
    spare = 2 if source != 2 else 1
    if free == spare:
        spare = 3
    if v != 0.0:
        _translate(pool[slot], pool[free], dims, masks[0], v, cos, sin, one_cell, masks[1])
        if corners.shape[0] > 0:
            _corner_loss(pool[slot], pool[free], masks[0], corners)
        masks[0, :, :] = masks[1]
        slot, free = free, (spare if slot == source else slot)
    if z_shift[0] != 0.0:
        _shift_outer(pool[slot], pool[free], dims, masks[0], int(z_shift[1]), z_shift[2], z_shift[3])
        slot, free = free, (spare if slot == source else slot)
    if th_shift[0] != 0.0:
        n_rows = _rows(masks[0], dims, rows)
        _shift_heading(pool[slot], pool[free], rows, n_rows, int(th_shift[1]), th_shift[2], th_shift[3])
        masks[0, 3, :] = True
        slot = free
    return slot


def on_odo(
    pool: np.ndarray, source: int, dims: np.ndarray, masks: np.ndarray, rows: np.ndarray,
    e_offsets: np.ndarray, e_weights: np.ndarray, e_counts: np.ndarray, e_signed: np.ndarray,
    i_offsets: np.ndarray, i_weights: np.ndarray, i_counts: np.ndarray, i_signed: np.ndarray, inhibition: float,
    best: np.ndarray, v: float, cos: np.ndarray, sin: np.ndarray, one_cell: bool, corners: np.ndarray,
    z_shift: np.ndarray, th_shift: np.ndarray, x_first: bool,
) -> tuple[int, np.ndarray]:  # fmt: skip
    """:func:`attractor`, :func:`path_integrate` and :func:`peak` in one call; return (the result's slot, its peak)."""
    slot, _ = attractor(pool, source, dims, masks, rows, e_offsets, e_weights, e_counts, e_signed, i_offsets,
                        i_weights, i_counts, i_signed, inhibition, best)
    slot = path_integrate(pool, slot, dims, masks, rows, True, v, cos, sin, one_cell, corners, z_shift, th_shift)
    return slot, peak(pool[slot], dims, masks[0], x_first)


def peak(cells: np.ndarray, dims: np.ndarray, masks: np.ndarray, x_first: bool) -> np.ndarray:
    """Return (x, y, z, θ) of the first maximum scanning θ outermost, then z, y, x (or x, y, z when ``x_first``).

    Only the slices in ``masks`` are visited (every other cell is 0); an all-zero lattice gives (0, 0, 0, 0).
    """
    nx, ny, nz = dims[0], dims[1], dims[2]
    best = np.zeros(4, np.int64)
    top = 0.0
    for t in range(cells.shape[1]):
        if not masks[3, t]:
            continue
        for a in range(nz if not x_first else nx):
            for b in range(ny):
                for c in range(nx if not x_first else nz):
                    x, z = (c, a) if not x_first else (a, c)
                    if masks[0, x] and masks[1, b] and masks[2, z]:
                        value = cells[(x * ny + b) * nz + z, t]
                        if value > top:
                            top = value
                            best[0], best[1], best[2], best[3] = x, b, z, t
    return best

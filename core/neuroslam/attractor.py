"""A continuous attractor network on a wrapping N-D lattice, as NeuroSLAM's two networks use it.

NeuroSLAM (Yu et al. 2019, §4.2) runs the same dynamics on its 3-D grid-cell cube (x, y, z) and on its
multilayer head-direction sheet (yaw, height); notes ``neuroslam.md`` §1–3. One step, in the order of the
authors' code (§6):

1. local excitation, Eqs. (1)–(3): ``P ← P ⊛ e``, a wrapped convolution with a truncated Gaussian ``e``
   normalised to sum 1; the result replaces ``P`` (Eq. 2 as printed lacks the weight: a typo);
2. local inhibition, Eq. (4): ``P ← P − P ⊛ ψ`` with a second normalised Gaussian ``ψ``;
3. global inhibition, Eq. (4): ``P ← max(P − φ, 0)``;
4. normalisation, Eq. (5): ``P ← P / ΣP``;
5. path integration, Eqs. (6)–(9) and (17)–(20): a fractional wrapped shift along each axis.

A kernel of ``n`` cells covers offsets ``−⌊n/2⌋ … n − 1 − ⌊n/2⌋`` (the head-direction sheet's 8-cell kernel
is asymmetric, −4 … +3, as in the authors' code). The Gaussians are separable, so a kernel is applied one axis
at a time. The work follows the packet: each filter runs on the smallest wrapped box that holds the active
cells, widened by the kernel's reach, so a step costs (box cells × taps), not (lattice cells × kernel cells);
an axis that the widened box would cover whole is filtered around the lattice instead. Sums run in a fixed
order, so a step gives the same bits every run.

The shift is exact for any fractional distance (linear interpolation between the two cells a packet lands
between, on every axis at once): the authors' per-layer rotate-and-shift loses a spill cell per row and
column and needs |v| ≤ 1 cell a frame (notes §1.4); this one loses nothing.

Decoding (notes §3, not in the paper): the peak cell, a wrapped window of ± ``window`` cells around it, and a
population vector per axis, ``atan2(Σ v sin(iθ), Σ v cos(iθ)) / θ mod N`` with ``θ = 2π/N``: a fractional cell
index in [0, N). Cells are numbered from 0 here (the authors' code numbers from 1; the codes differ by one
cell, a constant offset that no decision depends on).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class Taps:
    """A 1-D filter: weight ``weights[i]`` moves activity by ``offsets[i]`` cells along one axis."""

    offsets: tuple[int, ...]
    weights: tuple[float, ...]

    @property
    def reach(self) -> int:
        """How far (in cells) the filter moves activity, either way."""
        return max(abs(o) for o in self.offsets)


@dataclass(frozen=True)
class Kernel:
    """A separable kernel: one :class:`Taps` per axis, the product of which is the N-D kernel."""

    axes: tuple[Taps, ...]

    @classmethod
    def gaussian(cls, sizes: tuple[int, ...], sigmas: tuple[float, ...]) -> Kernel:
        """The separable Gaussian of Eq. (1) / (12) on ``sizes`` cells per axis, normalised to sum 1.

        The product of 1-D Gaussians each normalised to 1 is the N-D Gaussian normalised to 1.
        """
        axes = []
        for n, sigma in zip(sizes, sigmas, strict=True):
            offsets = np.arange(n, dtype=np.int64) - n // 2
            weights = np.exp(-(offsets * offsets) / (2.0 * sigma * sigma))
            weights /= weights.sum()
            axes.append(Taps(tuple(int(o) for o in offsets), tuple(float(w) for w in weights)))
        return cls(tuple(axes))


def _shift_taps(cells: float) -> Taps:
    """Linear interpolation between the two cells that ``cells`` (fractional) falls between."""
    whole = math.floor(cells)
    frac = cells - whole
    return Taps((whole, whole + 1), (1.0 - frac, frac))


def _filter_axis(block: FloatArray, axis: int, taps: Taps, circular: bool) -> FloatArray:
    """Apply ``taps`` along ``axis``: around the lattice when ``block`` spans it, else with zeros outside."""
    out = np.zeros_like(block)
    n = block.shape[axis]
    for offset, weight in zip(taps.offsets, taps.weights, strict=True):
        if circular:
            out += weight * np.roll(block, offset, axis=axis)
            continue
        if abs(offset) >= n:
            continue
        target = [slice(None)] * block.ndim
        source = [slice(None)] * block.ndim
        target[axis] = slice(max(offset, 0), n + min(offset, 0))
        source[axis] = slice(max(-offset, 0), n - max(offset, 0))
        out[tuple(target)] += weight * block[tuple(source)]
    return out


def _covering_cells(occupied: IntArray, n: int, margin: int) -> IntArray | None:
    """The cells of the shortest wrapped interval holding ``occupied``, widened by ``margin`` each side.

    ``None`` when the widened interval would cover the whole axis (then the axis is filtered around the lattice).
    """
    gaps = np.diff(np.append(occupied, occupied[0] + n))
    widest = int(np.argmax(gaps))
    start = int(occupied[(widest + 1) % len(occupied)])
    length = n - int(gaps[widest]) + 1
    if length + 2 * margin >= n:
        return None
    return (start - margin + np.arange(length + 2 * margin, dtype=np.int64)) % n


class WrappedAttractor:
    """Activity on a wrapping lattice of ``dims`` cells; each step works on the box that holds the packet."""

    def __init__(self, dims: tuple[int, ...], excite: Kernel, inhibit: Kernel, global_inhibition: float,
                 window: int) -> None:
        self.dims = dims
        self.excite = excite
        self.inhibit = inhibit
        self.global_inhibition = global_inhibition
        self.window = window
        self.activity: FloatArray = np.zeros(dims, dtype=np.float64)
        self._dims = np.asarray(dims, dtype=np.int64)

    def set_single(self, cell: tuple[int, ...]) -> None:
        """All activity on one cell (the networks' starting state, notes §2)."""
        self.activity[...] = 0.0
        self.activity[cell] = 1.0

    def inject(self, cell: tuple[int, ...], energy: float) -> None:
        """Add ``energy`` to one cell, wrapped onto the lattice (view calibration, notes §1.5)."""
        wrapped = tuple(int(c) % n for c, n in zip(cell, self.dims, strict=True))
        self.activity[wrapped] += energy

    def _filter(self, activity: FloatArray, kernels: list[Kernel]) -> FloatArray:
        """Apply ``kernels`` to ``activity`` in turn, each separably, on the box of cells its packet can reach."""
        ndim = len(self.dims)
        cells: list[IntArray | None] = []
        for axis in range(ndim):
            others = tuple(a for a in range(ndim) if a != axis)
            occupied = np.flatnonzero(np.any(activity != 0.0, axis=others)).astype(np.int64)
            margin = sum(k.axes[axis].reach for k in kernels)
            cells.append(_covering_cells(occupied, self.dims[axis], margin))
        index = np.ix_(*[np.arange(n) if c is None else c for c, n in zip(cells, self.dims, strict=True)])
        block = activity[index]
        for kernel in kernels:
            for axis, taps in enumerate(kernel.axes):
                block = _filter_axis(block, axis, taps, circular=cells[axis] is None)
        result = np.zeros_like(activity)
        result[index] = block
        return result

    def step_attractor(self) -> None:
        """Excite, inhibit locally and globally, normalise: Eqs. (2), (4), (5) (and (13), (15), (16))."""
        if not self.activity.any():
            return
        excited = self._filter(self.activity, [self.excite])
        inhibited = excited - self._filter(excited, [self.inhibit])
        clamped = np.maximum(inhibited - self.global_inhibition, 0.0)
        total = float(clamped.sum())
        if total > 0.0:
            self.activity = clamped / total
        # A packet inhibited to nothing keeps its previous activity (the paper's networks assume it never is).

    def shift(self, cells: tuple[float, ...]) -> None:
        """Move the packet by ``cells`` (fractional, any size) along each axis: Eqs. (6)–(9), (17)–(20)."""
        if not self.activity.any():
            return
        self.activity = self._filter(self.activity, [Kernel(tuple(_shift_taps(c) for c in cells))])

    def decode(self) -> FloatArray:
        """Fractional cell index of the packet on each axis: the windowed population vector (notes §3)."""
        peak = np.array(np.unravel_index(int(np.argmax(self.activity)), self.dims), dtype=np.int64)
        span = np.arange(-self.window, self.window + 1, dtype=np.int64)
        grids = np.meshgrid(*[span] * len(self.dims), indexing="ij")
        offsets = np.stack([g.ravel() for g in grids], axis=1)
        cells = (peak + offsets) % self._dims
        # A window wider than an axis would count its cells twice: keep each cell once.
        flat_cells = np.unique(np.ravel_multi_index(tuple(cells.T), self.dims))
        values = self.activity.ravel()[flat_cells]
        coords = np.stack(np.unravel_index(flat_cells, self.dims), axis=1).astype(np.float64)
        theta = 2.0 * np.pi / self._dims.astype(np.float64)
        angles = coords * theta
        centre = np.mod(np.arctan2(values @ np.sin(angles), values @ np.cos(angles)) / theta, self._dims)
        # np.mod of a tiny negative number rounds up to N itself: that cell is 0.
        return np.where(centre >= self._dims, 0.0, centre)

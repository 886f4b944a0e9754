"""Pose cells: a continuous attractor network on a wrapping (x, y, [z,] θ) lattice.

Implements OpenRatSLAM's ``PosecellNetwork`` (Ball et al. 2013; anchors §1.1) in
the RatSLAM notation of Menezes et al. (2023) §2.1–2.2, generalised to the 4-DoF
(x, y, z, ψ) lattice of PoseidonSLAM (thesis §4.2.4, Eqs. 4.16–4.19):

* attractor dynamics ``on_odo``: excite (Eq. 1–3 excitatory part), inhibit,
  global inhibition φ, normalise to 1, path integration, population-vector decode;
* the LVC→pose-cell link table β (Eq. 4 / 4.19) with OpenRatSLAM's injection
  saturation ``δ/30·(30 − e^{1.2·decay})`` (Eq. 5).

Array layout is ``activity[x, y, (z,) th]``. Coordinates are in cells.

Checked against OpenRatSLAM's code: update order, circulant excite/inhibit with
σ = ``pc_w_*_var``, global inhibition floored at 0, normalisation, per-layer
translation (layer k heads k·2π/n_θ) then the θ shift with floor/ceil weights,
the first-maximum peak in θ-outermost scan order, ±3-cell population-vector
decoding (its (i+1)-based lookups and "− 1" cancel), links created once per new
template at the packet centre with decay ``vt_active_decay``, injection at the
truncated link cell, and ``vt_delta_pc_th`` updated only when energy is injected.

Deliberate deviations:

* translations of more than one cell per frame are exact (OpenRatSLAM's
  four-neighbour weights turn negative there);
* with fewer than ``vt_min_inject_age`` (10) templates nothing injects: the rule
  ``template < count − 10`` is applied as written (OpenRatSLAM's unsigned
  ``size() − 10`` wraps around for fewer than 10 templates and lets every
  known template inject);
* the decoding window is narrowed on axes shorter than 2·``pc_cells_to_avg`` + 1
  (OpenRatSLAM would count cells twice); a fully inhibited network restarts at
  the last decoded centre (OpenRatSLAM asserts).

With ``openratslam_compat`` the first two follow OpenRatSLAM's code: a translation
of s cells (any size) keeps weight 1 − |s| in place and moves |s| one cell, and
while fewer than ``vt_min_inject_age`` templates exist every known one injects.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING

import numpy as np

from core._buffers import GrowBuffer
from core.config import Departure
from core.lattice import circulant_kernel, wrapped_distance

if TYPE_CHECKING:
    from core.config import Params

SPARSE_FRACTION = 8  # attractor steps on the active block when it spans at most 1/8 of the lattice


class PoseCellNetwork:
    """Pose-cell activity, its dynamics and the view-template links.

    Args:
        params: engine parameters (``pc_*``, ``vt_active_decay``, ``vt_min_inject_age``).
    """

    def __init__(self, params: Params) -> None:
        self.params = params
        self.shape: tuple[int, ...] = tuple(int(d) for d in params.lattice_shape)
        self.rank = len(self.shape)
        self.dims = np.asarray(self.shape, dtype=np.float64)
        self.activity = np.zeros(self.shape, dtype=np.float64)
        centre = tuple(d // 2 for d in self.shape)
        self.activity[centre] = 1.0
        self.best = np.asarray(centre, dtype=np.float64)
        self.current_vt = -1
        self.prev_vt = -1
        self.vt_delta_th = 0.0
        self._links_template = GrowBuffer((), np.int64)
        self._links_coords = GrowBuffer((self.rank,), np.float64)
        self._links_strength = GrowBuffer((), np.float64)
        self._links_decay = GrowBuffer((), np.float64)
        self._links_of_template: list[list[int]] = []
        self._build_operators()

    # ------------------------------------------------------------------ setup
    def _build_operators(self) -> None:
        p = self.params
        # Excitation then inhibition, each a separable wrapped Gaussian: one circulant matrix per axis.
        self._excite = [circulant_kernel(d, p.pc_w_e_dim, p.pc_w_e_var) for d in self.shape]
        self._inhibit = [circulant_kernel(d, p.pc_w_i_dim, p.pc_w_i_var) for d in self.shape]
        # each kernel's reach: the offsets (mod d) it spreads a cell to — column 0 of the circulant
        self._excite_reach = [np.flatnonzero(m[:, 0]) for m in self._excite]
        self._inhibit_reach = [np.flatnonzero(m[:, 0]) for m in self._inhibit]
        # can a packet block ever be small enough? (even one active cell reaches both kernels' widths)
        widths = zip(self.shape, self._excite_reach, self._inhibit_reach, strict=True)
        smallest = math.prod(min(d, e.size + i.size - 1) for d, e, i in widths)
        self._blocks = SPARSE_FRACTION * smallest <= math.prod(self.shape)
        th_dim = self.shape[-1]
        angles = np.arange(th_dim, dtype=np.float64) * (2.0 * math.pi / th_dim)
        # exact zeros on the axis-aligned layers, so integer moves stay integer
        self._layer_cos = np.where(np.abs(np.cos(angles)) < 1e-12, 0.0, np.cos(angles))
        self._layer_sin = np.where(np.abs(np.sin(angles)) < 1e-12, 0.0, np.sin(angles))
        # Population-vector decoding lookups (OpenRatSLAM find_best; its (i+1)-based tables and the
        # final "− 1" cancel, so cell i sits at angle i·2π/n here).
        self._sin_lookup = [np.sin(np.arange(d) * 2.0 * math.pi / d) for d in self.shape]
        self._cos_lookup = [np.cos(np.arange(d) * 2.0 * math.pi / d) for d in self.shape]
        radius = int(p.pc_cells_to_avg)
        self._window_offsets = [np.arange(-min(radius, (d - 1) // 2), min(radius, (d - 1) // 2) + 1)
                                for d in self.shape]
        self._marginal_axes = [tuple(a for a in range(self.rank) if a != axis) for axis in range(self.rank)]
        # Scratch arrays reused every frame: large lattices (the 4-DoF one is 216 kB) would otherwise pay
        # for fresh pages on every temporary. ``activity`` is always a separate array or one of the pool.
        heading_first = (th_dim, *self.shape[:-1])
        self._pool = [np.empty(self.shape, dtype=np.float64) for _ in range(5)]
        self._pool_th = [np.empty(heading_first, dtype=np.float64) for _ in range(3)]

    def _scratch(self, count: int) -> list[np.ndarray]:
        """Return ``count`` pool arrays that are not the current activity."""
        return [buf for buf in self._pool if buf is not self.activity][:count]

    # ------------------------------------------------------------- dynamics
    def step_attractor(self) -> None:
        """Run excite, inhibit, global inhibition and normalisation (OpenRatSLAM ``on_odo`` steps 1–4).

        Eq. 3 of Menezes et al.: ΔP = Σ P·ε − φ, then P is clipped at 0 and
        normalised to total activity 1. Excitation spreads every cell through the
        ``pc_w_e_dim``-cube Gaussian (σ = ``pc_w_e_var``), wrapping across every face;
        inhibition subtracts the ``pc_w_i_dim``-cube spread of the excited activity.
        Both cubes are separable, so each is applied as one small circulant matrix
        product per axis (equal to OpenRatSLAM's cell-by-cell spread up to rounding).

        Like OpenRatSLAM, which visits only active cells, the work follows the
        packet: when the active cells' slices, widened by the two kernels' reach,
        span at most ``1/SPARSE_FRACTION`` of the lattice, only that block is
        computed — every cell outside it gets no excitation or inhibition and
        ends at max(0 − φ, 0) = 0, exactly as in the full computation.
        """
        p = self.params
        region = self._active_region()
        if region is None:
            w0, w1, w2, w3 = self._scratch(4)
            excited = _separable(self.activity, self._excite, w0, w1)
            inhibited = _separable(excited, self._inhibit, w2, w3)
            cells = np.subtract(excited, inhibited, out=excited)
            total = _inhibit_globally_and_normalise(cells, p.pc_global_inhib)
        else:
            source, spread, reach = region
            block = self.activity[np.ix_(*source)]
            excite = [m[np.ix_(o, i)] for m, o, i in zip(self._excite, spread, source, strict=True)]
            excited = _apply_axes(block, excite)  # on the spread slices
            inhibit = [m[np.ix_(o, i)] for m, o, i in zip(self._inhibit, reach, spread, strict=True)]
            local = np.negative(_apply_axes(excited, inhibit))  # on the reach slices (⊇ spread)
            inside = [np.searchsorted(r, s) for r, s in zip(reach, spread, strict=True)]
            local[np.ix_(*inside)] += excited
            total = _inhibit_globally_and_normalise(local, p.pc_global_inhib)
            cells = self._scratch(1)[0]
            cells.fill(0.0)
            cells[np.ix_(*reach)] = local
        if not total > 0.0:  # everything inhibited (OpenRatSLAM asserts): restart from the decoded packet centre
            cells[...] = 0.0
            cells[tuple(int(b) % d for b, d in zip(self.best, self.shape, strict=True))] = 1.0
        self.activity = cells

    def _active_region(self) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]] | None:
        """Return per-axis sorted cell indices (active, after excitation, after inhibition), or None.

        ``active``: the slices holding activity; ``spread``: those the excitation
        kernel reaches from them; ``reach``: those the inhibition kernel reaches from
        ``spread`` (always ⊇ ``spread``). None when the block is too large to pay off
        (more than 1/``SPARSE_FRACTION`` of the cells) or nothing is active.
        """
        if not self._blocks:
            return None
        active = _occupied(self.activity, range(self.rank))
        if active[0].size == 0:
            return None
        spread = [_reach(a, off, d) for a, off, d in zip(active, self._excite_reach, self.shape, strict=True)]
        reach = [
            np.union1d(_reach(s, off, d), s) for s, off, d in zip(spread, self._inhibit_reach, self.shape, strict=True)
        ]
        if SPARSE_FRACTION * math.prod(r.size for r in reach) > self.activity.size:
            return None
        return active, spread, reach

    def path_integrate(self, forward_m: float, dyaw_rad: float, dz_m: float = 0.0) -> None:
        """Shift the packet by odometry (OpenRatSLAM ``path_integration``).

        Each heading layer θ_k = k·2π/n_θ is translated by ``forward/pc_cell_x_size``
        cells along (cos θ_k, sin θ_k) with bilinear weights: x then y, each split
        between the two nearest integer shifts. For moves under one cell these are
        OpenRatSLAM's four-neighbour weights (sw, se, nw, ne); larger moves, which
        OpenRatSLAM does not support (its weights turn negative), stay exact here.
        A negative forward motion moves against the layer heading (OpenRatSLAM adds π).
        Then z is shifted by ``dz/pc_cell_z_size`` cells and θ by ``dyaw/(2π/n_θ)``
        cells, each with linear weights between the floor and ceiling shifts (as
        OpenRatSLAM's θ shift). Every shift wraps across the lattice faces.
        """
        p = self.params
        v = forward_m / p.pc_cell_x_size
        moved_z = self.rank == 4 and dz_m != 0.0
        if v == 0.0 and dyaw_rad == 0.0 and not moved_z:
            return
        th_dim = self.shape[-1]
        # Work heading-first, (θ, x, y, [z]): per-layer shifts become batched matrix products.
        a, b, c = self._pool_th
        np.copyto(a, np.moveaxis(self.activity, -1, 0))
        if v != 0.0:
            dim_x, dim_y = self.shape[0], self.shape[1]
            # Only heading layers holding activity move anything (a packet spans a few of them): the
            # others stay zero, and each layer's product is computed exactly as in a full batch.
            layers = np.flatnonzero(a.reshape(th_dim, -1).any(axis=1))
            one_cell = p.follows_openratslam(Departure.TRANSLATION)
            before = a[layers].copy() if one_cell else None
            shift_x = _shift_matrices(v * self._layer_cos[layers], dim_x, one_cell)  # (L, X, X)
            shift_y = _shift_matrices(v * self._layer_sin[layers], dim_y, one_cell)  # (L, Y, Y)
            moving = a[layers]
            compact = self._blocks
            if compact:
                rows, cols = _occupied(moving, (1, 2))
                compact = SPARSE_FRACTION * rows.size * cols.size <= dim_x * dim_y
            if compact:
                # a compact packet: move only its rows and columns, to the rows and columns they reach
                shift_x = shift_x[:, :, rows]
                shift_y = shift_y[:, :, cols]
                to_rows = np.flatnonzero(shift_x.any(axis=(0, 2)))
                to_cols = np.flatnonzero(shift_y.any(axis=(0, 2)))
                shift_x = shift_x[:, to_rows]
                shift_y = shift_y[:, to_cols]
                moving = moving[:, rows][:, :, cols]
                a[layers] = 0.0
                target = np.ix_(layers, to_rows, to_cols)
            else:
                target = (layers,)
            count, span_x, span_y = moving.shape[:3]
            if self.rank == 3:
                moved = np.matmul(np.matmul(shift_x, moving), shift_y.transpose(0, 2, 1))
            else:
                moved = np.matmul(shift_x, moving.reshape(count, span_x, -1)).reshape(
                    count, shift_x.shape[1], span_y, -1
                )
                moved = np.matmul(shift_y[:, None], moved)
            a[target] = moved
            if before is not None:
                _openratslam_corner_loss(a, before, layers, v)
        if moved_z:
            a, b = _shift_axis(a, dz_m / p.pc_cell_z_size, 3, b, c), a
        if dyaw_rad != 0.0:
            a, b = _shift_axis(a, dyaw_rad / (2.0 * math.pi / th_dim), 0, b, c), a
        out = self._scratch(1)[0]
        np.copyto(out, np.moveaxis(a, 0, -1))
        self.activity = out

    def decode(self) -> np.ndarray:
        """Return the packet centre by population vector around the peak (OpenRatSLAM ``find_best``).

        The peak is the first maximum in OpenRatSLAM's scan order (θ outermost, x
        innermost). Its ±``pc_cells_to_avg`` wrapped window (narrowed on axes too
        short for it, so no cell counts twice) is summed per axis and each axis
        decoded as the circular mean ``atan2(Σ s·sin, Σ s·cos)·n/(2π)`` in [0, n).
        """
        if self.params.follows_openratslam(Departure.DECODE):
            return self._decode_openratslam()
        cells = self.activity
        flat = int(np.argmax(cells.T))  # reversed axes: (θ, [z,] y, x) scan order
        peak = np.unravel_index(flat, self.shape[::-1])[::-1]
        windows = [(int(c) + off) % d for c, off, d in zip(peak, self._window_offsets, self.shape, strict=True)]
        box = cells[np.ix_(*windows)]
        best = np.empty(self.rank, dtype=np.float64)
        for axis in range(self.rank):
            marginal = box.sum(axis=self._marginal_axes[axis])
            idx = windows[axis]
            s = float(np.dot(marginal, self._sin_lookup[axis][idx]))
            c = float(np.dot(marginal, self._cos_lookup[axis][idx]))
            dim = self.shape[axis]
            value = math.atan2(s, c) * dim / (2.0 * math.pi)
            value = math.fmod(value, dim)
            if value < 0.0:
                value += dim
            best[axis] = value if value < dim else 0.0
        self.best = best
        return best

    def _decode_openratslam(self) -> np.ndarray:
        """``find_best`` as OpenRatSLAM's code computes it, to the last bit where it can (``openratslam_compat``).

        OpenRatSLAM's lattice is ours transposed in x and y (its heading-0 layer moves along its second
        axis), so its scan order is (θ, x, y) in ours. Its per-axis sums add cells in its loop order,
        its lookups are (i+1)-based with a final "− 1", and its wrap leaves values in [0, n]. These
        change the decoded centre by ~1e-15 of a cell, but that decides the cell a new template's link
        truncates to (16.999999999999996 → 16, not 17).
        """
        cells = self.activity
        scan = (self.rank - 1, *range(self.rank - 1))
        flat = int(np.argmax(cells.transpose(scan)))
        peak = [0] * self.rank
        for axis, index in zip(scan, np.unravel_index(flat, [self.shape[a] for a in scan]), strict=True):
            peak[axis] = int(index)
        windows = [(c + off) % d for c, off, d in zip(peak, self._window_offsets, self.shape, strict=True)]
        box = cells[np.ix_(*windows)]
        best = np.empty(self.rank, dtype=np.float64)
        for axis in range(self.rank):
            order = [a for a in scan if a != axis]
            marginal = np.ascontiguousarray(box.transpose((*order, axis))).reshape(-1, box.shape[axis]).sum(axis=0)
            dim = self.shape[axis]
            s = c = 0.0
            for k in np.argsort(windows[axis], kind="stable"):  # index order, as its loop over the whole axis
                angle = (int(windows[axis][k]) + 1) * 2.0 * math.pi / dim
                s += math.sin(angle) * float(marginal[k])
                c += math.cos(angle) * float(marginal[k])
            value = math.atan2(s, c) * dim / (2.0 * math.pi) - 1.0
            while value < 0.0:
                value += dim
            while value > dim:
                value -= dim
            best[axis] = value
        self.best = best
        return best

    def on_odo(self, forward_m: float, dyaw_rad: float, dz_m: float = 0.0) -> np.ndarray:
        """Run one OpenRatSLAM ``on_odo`` update and return the decoded packet centre."""
        self.step_attractor()
        self.path_integrate(forward_m, dyaw_rad, dz_m)
        return self.decode()

    def inject(self, coords: np.ndarray, energy: float) -> None:
        """Add ``energy`` to the cell at ``coords`` truncated to integers (OpenRatSLAM ``inject``)."""
        cell = tuple(int(c) % d for c, d in zip(coords, self.shape, strict=True))
        self.activity[cell] += energy

    # ------------------------------------------------------------ view links
    @property
    def link_count(self) -> int:
        """Return the number of LVC→pose-cell links."""
        return len(self._links_template)

    def add_link(self, template: int, coords: np.ndarray, strength: float = 1.0, decay: float | None = None) -> int:
        """Add a link β from ``template`` to lattice ``coords`` (Menezes Eq. 4) and return its index."""
        index = self._links_template.append(template)
        self._links_coords.append(coords)
        self._links_strength.append(strength)
        self._links_decay.append(self.params.vt_active_decay if decay is None else decay)
        while len(self._links_of_template) <= template:
            self._links_of_template.append([])
        self._links_of_template[template].append(index)
        return index

    def links_of(self, template: int) -> list[int]:
        """Return the link indices of ``template``."""
        if 0 <= template < len(self._links_of_template):
            return self._links_of_template[template]
        return []

    def on_view_template(self, template: int, relative_rad: float, template_count: int, created: bool) -> None:
        """Handle the view-template stream (OpenRatSLAM ``on_view_template``).

        A new template is linked to the current packet centre (decay
        ``vt_active_decay``). A known template older than ``vt_min_inject_age``
        creations (``template < template_count − vt_min_inject_age``) injects, through
        each of its links, ``pc_vt_inject_energy·strength/30·(30 − e^{1.2·decay})`` at
        the link cell truncated to integers, θ offset by the view's ``relative_rad``;
        seeing the same template again first raises its decay by ``vt_active_decay``
        (saturation). When energy is injected the heading offset
        ``vt_delta_th = relative_rad/(2π)·n_θ`` used by :meth:`delta_to` is updated (it
        keeps its last value otherwise, as in OpenRatSLAM). Every link's decay then
        relaxes by ``pc_vt_restore`` down to ``vt_active_decay``.
        """
        p = self.params
        th_dim = self.shape[-1]
        if created:
            self.add_link(template, self.best.copy())
        elif template < template_count - p.vt_min_inject_age or (
            template_count < p.vt_min_inject_age and p.follows_openratslam(Departure.INJECTION)  # unsigned wrap-around
        ):
            decay = self._links_decay.view
            coords_all = self._links_coords.view
            strength = self._links_strength.view
            offset = relative_rad / (2.0 * math.pi) * th_dim
            for link in self.links_of(template):
                if template == self.current_vt:
                    decay[link] += p.vt_active_decay
                # exp capped: a template seen for ~600 frames in a row overflows math.exp (OpenRatSLAM: inf)
                saturation = math.exp(min(1.2 * decay[link], 700.0))
                energy = p.pc_vt_inject_energy * strength[link] / 30.0 * (30.0 - saturation)
                if energy > 0.0:
                    self.vt_delta_th = offset
                    coords = coords_all[link].copy()
                    coords[-1] = (coords[-1] + offset) % th_dim
                    self.inject(coords, energy)
        if len(self._links_decay):
            decay = self._links_decay.view
            decay -= p.pc_vt_restore
            np.maximum(decay, p.vt_active_decay, out=decay)
        self.prev_vt = self.current_vt
        self.current_vt = template

    def delta_to(self, coords: np.ndarray) -> np.ndarray:
        """Return wrapped lattice distances from the heading-corrected packet centre to ``coords`` (…, D).

        OpenRatSLAM ``get_delta_pc``: the current θ is corrected by the view's
        relative heading before the wrapped Euclidean distance is taken.
        """
        best = self.best.copy()
        best[-1] = (best[-1] - self.vt_delta_th) % self.shape[-1]
        return wrapped_distance(best, coords, self.dims)

    # ------------------------------------------------------------- snapshot
    def snapshot(self) -> dict[str, np.ndarray]:
        """Return the pose-cell state as plain arrays (keys ``pc_*`` of docs/architecture.md)."""
        return {
            "pc_activity": self.activity.copy(),
            "pc_best": self.best.copy(),
            "pc_link_template": self._links_template.copy(),
            "pc_link_coords": self._links_coords.copy(),
            "pc_link_strength": self._links_strength.copy(),
            "pc_link_decay": self._links_decay.copy(),
            "pc_current_vt": np.asarray(self.current_vt, dtype=np.int64),
            "pc_prev_vt": np.asarray(self.prev_vt, dtype=np.int64),
            "pc_vt_delta_th": np.asarray(self.vt_delta_th, dtype=np.float64),
        }

    @classmethod
    def restore(cls, params: Params, state: Mapping[str, np.ndarray]) -> PoseCellNetwork:
        """Rebuild a network from :meth:`snapshot` arrays, exactly."""
        net = cls(params)
        activity = np.asarray(state["pc_activity"], dtype=np.float64)
        if activity.shape != net.shape:
            msg = f"pose-cell activity shape {activity.shape} does not match the parameters' lattice {net.shape}"
            raise ValueError(msg)
        net.activity = activity.copy()
        net.best = np.asarray(state["pc_best"], dtype=np.float64).copy()
        templates = np.asarray(state["pc_link_template"], dtype=np.int64)
        coords = np.asarray(state["pc_link_coords"], dtype=np.float64).reshape(-1, net.rank)
        strength = np.asarray(state["pc_link_strength"], dtype=np.float64)
        decay = np.asarray(state["pc_link_decay"], dtype=np.float64)
        net._links_template = GrowBuffer.from_array(templates, np.int64)
        net._links_coords = GrowBuffer.from_array(coords, np.float64)
        net._links_strength = GrowBuffer.from_array(strength, np.float64)
        net._links_decay = GrowBuffer.from_array(decay, np.float64)
        n_templates = int(templates.max()) + 1 if templates.size else 0
        net._links_of_template = [[] for _ in range(n_templates)]
        for index, template in enumerate(templates.tolist()):
            net._links_of_template[template].append(index)
        net.current_vt = int(state["pc_current_vt"])
        net.prev_vt = int(state["pc_prev_vt"])
        net.vt_delta_th = float(state["pc_vt_delta_th"])
        return net


def _inhibit_globally_and_normalise(cells: np.ndarray, inhibition: float) -> float:
    """Subtract global inhibition φ, clip at 0 and scale to total 1, in place (Eq. 3); return the pre-scale total."""
    cells -= inhibition
    np.maximum(cells, 0.0, out=cells)
    total = float(cells.sum())
    if total > 0.0:
        cells /= total
    return total


def _occupied(cells: np.ndarray, axes: Iterable[int]) -> list[np.ndarray]:
    """Return, for each axis in ``axes``, the sorted indices of the slices of ``cells`` holding a non-zero."""
    nonzero = cells != 0.0
    return [np.flatnonzero(nonzero.any(axis=tuple(i for i in range(cells.ndim) if i != a))) for a in axes]


def _reach(indices: np.ndarray, offsets: np.ndarray, dim: int) -> np.ndarray:
    """Return the sorted distinct ``(i + o) mod dim`` for i in ``indices`` and o in ``offsets``."""
    return np.unique((indices[:, None] + offsets[None, :]) % dim)


def _apply_axes(block: np.ndarray, matrices: list[np.ndarray]) -> np.ndarray:
    """Apply ``matrices[a]`` (out_a × in_a) along every axis a of ``block`` in turn; return the new block."""
    out = block
    for axis, matrix in enumerate(matrices):
        out = np.moveaxis(np.tensordot(matrix, out, axes=([1], [axis])), 0, axis)
    return out


def _separable(cells: np.ndarray, matrices: list[np.ndarray], even: np.ndarray, odd: np.ndarray) -> np.ndarray:
    """Apply one (d, d) matrix along every axis of ``cells`` in turn (a separable wrapped convolution).

    The passes write alternately into ``even`` and ``odd`` (same shape as ``cells``);
    the one holding the result is returned.
    """
    shape = cells.shape
    last = len(shape) - 1
    src = cells
    for axis, matrix in enumerate(matrices):
        dst = even if axis % 2 == 0 else odd
        if axis == last:
            np.matmul(src.reshape(-1, shape[axis]), matrix.T, out=dst.reshape(-1, shape[axis]))
        else:
            lead = math.prod(shape[:axis])
            np.matmul(matrix, src.reshape(lead, shape[axis], -1), out=dst.reshape(lead, shape[axis], -1))
        src = dst
    return src


def _shift_matrices(shifts: np.ndarray, dim: int, one_cell: bool = False) -> np.ndarray:
    """Return (n, dim, dim) matrices moving a wrapped axis by ``shifts[k]`` cells with linear weights.

    Matrix k sends cell i to ``i + ⌊s_k⌋`` with weight ``1 − frac(s_k)`` and to
    ``i + ⌊s_k⌋ + 1`` with weight ``frac(s_k)``, modulo ``dim``. With ``one_cell``
    (OpenRatSLAM's four-neighbour weights, the same for |s| ≤ 1) cell i keeps
    ``1 − |s_k|`` and sends ``|s_k|`` to ``i ± 1``, whatever the size of ``s_k``.
    """
    n = shifts.shape[0]
    whole = np.where(shifts >= 0.0, 0.0, -1.0) if one_cell else np.floor(shifts)
    frac = shifts - whole
    columns = np.arange(dim)
    base = (np.arange(n) * (dim * dim))[:, None] + columns[None, :]
    rows0 = (columns[None, :] + whole.astype(np.int64)[:, None]) % dim
    rows1 = (rows0 + 1) % dim
    matrices = np.zeros(n * dim * dim, dtype=np.float64)
    matrices[base + rows0 * dim] = (1.0 - frac)[:, None]
    matrices[base + rows1 * dim] = frac[:, None]
    return matrices.reshape(n, dim, dim)


@functools.lru_cache(maxsize=64)
def _openratslam_rot90(dim: int, rot: int) -> np.ndarray:
    """Return ``r`` with ``r[j, i]`` = the flat index of the cell OpenRatSLAM's ``rot90_square`` moves to (j, i).

    Its in-place four-cycle rotation (float centre, truncating casts) run on an index grid.
    """
    grid = [[j * dim + i for i in range(dim)] for j in range(dim)]
    a, b, c, d = {1: (0, -1, 1, 0), 2: (-1, 0, 0, -1), 3: (0, 1, -1, 0)}.get(rot % 4, (1, 0, 0, 1))
    centre = (dim - 1) / 2.0
    turns = 0 if rot % 4 == 0 else (1 if rot % 2 == 1 else 2)
    if rot % 4 == 2:
        a, b, c, d = 0, -1, 1, 0
    for _ in range(turns):
        for j in range(int(centre) + (1 - dim % 2)):
            for i in range(int(centre) + 1):
                ii, jj, old = i, j, grid[j][i]
                for _quad in range(4):
                    ii, jj = (int(a * (ii - centre) + b * (jj - centre) + centre),
                              int(c * (ii - centre) + d * (jj - centre) + centre))
                    grid[jj][ii], old = old, grid[jj][ii]
    return np.asarray(grid, dtype=np.int64)


def _openratslam_corner_loss(cells: np.ndarray, before: np.ndarray, layers: np.ndarray, v: float) -> None:
    """Remove what OpenRatSLAM's translation loses at each layer's rotated corner (``openratslam_compat``).

    OpenRatSLAM rotates layer k by ⌊2·dir/π⌋ quarter turns (dir = k·2π/n_θ, + π when moving backwards),
    moves it by at most one cell towards +i and +j on a plane padded by one cell, then wraps the padding
    back — but its two wrap-back loops start at index 1, so what leaves rotated cell (0, n−1) along +i
    (weight ``v·sin·(1 − v·cos)``) and rotated cell (n−1, 0) along +j (weight ``v·cos·(1 − v·sin)``) never
    reaches rotated cell (0, 0). ``cells`` is heading-first (θ, x, y), our x being its j; ``before`` holds
    the moved layers before the move.
    """
    dim = cells.shape[1]
    th_dim = cells.shape[0]
    speed = abs(v)
    extra = math.pi if v < 0 else 0.0
    for plane, k in zip(before, layers.tolist(), strict=True):
        direction = k * (2.0 * math.pi / th_dim) + extra
        quarter = math.floor(direction * 2 / math.pi)
        dir90 = direction - quarter * math.pi / 2
        along_i = speed * math.sin(dir90) * (1.0 - speed * math.cos(dir90))
        along_j = speed * math.cos(dir90) * (1.0 - speed * math.sin(dir90))
        where = _openratslam_rot90(dim, int(quarter) % 4)
        lost = plane.flat[where[0, dim - 1]] * along_i + plane.flat[where[dim - 1, 0]] * along_j
        if lost != 0.0:
            cells[k].flat[where[0, 0]] -= lost


def _roll_into(src: np.ndarray, shift: int, axis: int, out: np.ndarray) -> np.ndarray:
    """Write ``np.roll(src, shift, axis)`` into ``out`` without a temporary."""
    n = src.shape[axis]
    k = shift % n
    lead = (slice(None),) * axis
    if k == 0:
        np.copyto(out, src)
    else:
        out[(*lead, slice(k, None))] = src[(*lead, slice(0, n - k))]
        out[(*lead, slice(0, k))] = src[(*lead, slice(n - k, None))]
    return out


def _shift_axis(cells: np.ndarray, shift: float, axis: int, out: np.ndarray, spare: np.ndarray) -> np.ndarray:
    """Shift ``cells`` along ``axis`` by a fractional number of cells, wrapping, with linear weights.

    The result is written into ``out`` (``spare`` is scratch); both differ from ``cells``.
    OpenRatSLAM's θ shift: ``(1 − w)·P[k − ⌊s⌋] + w·P[k − ⌊s⌋ − 1]`` with w = frac(s).
    """
    whole = math.floor(shift)
    frac = shift - whole
    _roll_into(cells, whole, axis, out)
    if frac == 0.0:
        return out
    _roll_into(cells, whole + 1, axis, spare)
    out *= 1.0 - frac
    spare *= frac
    out += spare
    return out

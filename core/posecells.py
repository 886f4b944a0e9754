"""Pose cells: a continuous attractor network on a wrapping (x, y, [z,] θ) lattice.

Implements OpenRatSLAM's ``PosecellNetwork`` (Ball et al. 2013; anchors §1.1) in
the RatSLAM notation of Menezes et al. (2023) §2.1–2.2, generalised to the 4-DoF
(x, y, z, ψ) lattice of PoseidonSLAM (thesis §4.2.4, Eqs. 4.16–4.19):

* attractor dynamics ``on_odo``: excite (Eq. 1–3 excitatory part), inhibit,
  global inhibition φ, normalise to 1, path integration, population-vector decode;
* the LVC→pose-cell link table β (Eq. 4 / 4.19) with OpenRatSLAM's injection
  saturation ``δ/30·(30 − e^{1.2·decay})`` (Eq. 5).

Array layout is ``activity[x, y, (z,) th]``. Coordinates are in cells.

Two paths compute ``on_odo`` with the same arithmetic, cell by cell, so they agree to the last bit: whole-lattice
numpy operations (the reference), and compiled loops over the slices that hold activity
(:mod:`core._posecell_kernel`, numba). A network takes the compiled path once the kernels are loaded: after
``COMPILED_AFTER`` cell updates (updates × lattice cells: the reference's cost), or before the first when
``mapserver process`` loads them for a long log.

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

By default these three run as OpenRatSLAM's code (``openratslam_parts`` = ``translation,injection,decode``),
so the engine takes OpenRatSLAM's decisions — template, action, experience — on every frame, and differs from it
only in the map it relaxes from them (:mod:`core.experience_map`). Chosen by ``bench/generalisation.py``: with
the exact translation the decisions part from OpenRatSLAM's within a few frames once the robot moves about one
cell a frame, and which loops close then is chance; on ``campus`` the default's APE ratio to OpenRatSLAM was
0.97–1.00 in median either way, but its 90th percentile 1.35 with the exact translation against 1.15 without
(seeds 0–13; ``street`` 0.77 against 0.70 in median). The departures stay options: ``openratslam_parts = none``.

``openratslam_parts`` (and ``openratslam_compat``, every part) runs each as OpenRatSLAM's code:
``translation`` — a translation of s cells (any size) keeps weight 1 − |s| in place and moves |s| one
cell, losing what wraps into each layer's rotated corner; ``injection`` — while fewer than
``vt_min_inject_age`` templates exist every known one injects; ``decode`` — ``find_best``'s scan
order, sums and rounding.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from core import _posecell_kernel as kernels
from core._buffers import GrowBuffer
from core.arrays import FloatArray, IntArray
from core.config import Departure
from core.lattice import circulant_kernel, wrapped_distance

if TYPE_CHECKING:
    from core.config import Params

COMPILED_AFTER = 3_000_000
"""Cell updates (``on_odo`` updates × lattice cells) after which a network loads the compiled kernels. numba's
import and the cached machine code take ~0.5 s, which the kernels repay within about this much reference work
(~200 updates of the 21×21×36 lattice, ~15 of the 80×80×35 one); short runs (tests, one-frame logs) never pay
it. The results are the same on either path."""


def worth_compiling(shape: tuple[int, ...], updates: int) -> bool:
    """Return whether ``updates`` updates of a lattice of ``shape`` reach ``COMPILED_AFTER`` cell updates."""
    return updates * math.prod(shape) >= COMPILED_AFTER

Taps = tuple[IntArray, FloatArray]
"""One separable factor of a kernel along one axis: (offsets o_k ascending, weights w_k)."""
_NO_SHIFT = np.zeros(4)
_NO_CORNERS = np.zeros((0, 5))


@dataclass(frozen=True, slots=True)
class Move:
    """One frame's path integration, as both paths apply it (:meth:`PoseCellNetwork.motion`).

    Heading layer t's plane moves ``v`` cells along (cos θ_t, sin θ_t), x then y (:func:`layer_moves`);
    ``one_cell``: OpenRatSLAM's four-neighbour weights whatever the size of the move (part ``translation``).
    ``corners`` (n_θ, 5) is OpenRatSLAM's per-layer translation loss (part ``translation``; else no rows).
    ``z`` and ``th`` = (apply, whole, keep, frac) of the z and θ shifts.
    """

    v: float
    one_cell: bool
    corners: FloatArray
    z: FloatArray
    th: FloatArray


_STILL = Move(0.0, False, _NO_CORNERS, _NO_SHIFT, _NO_SHIFT)


class PoseCellNetwork:
    """Pose-cell activity, its dynamics and the view-template links.

    ``activity`` may be written in place or replaced between updates. On the compiled path it is one of the
    network's reused buffers after an update: an array it held before must not be written to.

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
        self.updates = 0
        """``on_odo`` updates run by this network (not part of the state: a restored network counts from 0)."""
        self._links_template = GrowBuffer((), np.int64)
        self._links_coords = GrowBuffer((self.rank,), np.float64)
        self._links_strength = GrowBuffer((), np.float64)
        self._links_decay = GrowBuffer((), np.float64)
        self._links_of_template: list[list[int]] = []
        self._build_operators()
        self._buffers: _Buffers | None = None

    # ------------------------------------------------------------------ setup
    def _build_operators(self) -> None:
        p = self.params
        # Excitation then inhibition, each a separable wrapped Gaussian: one circulant factor per axis (its taps).
        self._excite = [_taps(circulant_kernel(d, p.pc_w_e_dim, p.pc_w_e_var)) for d in self.shape]
        self._inhibit = [_taps(circulant_kernel(d, p.pc_w_i_dim, p.pc_w_i_var)) for d in self.shape]
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

    def _compiled(self) -> _Buffers:
        """Return the compiled path's buffers (made on first use)."""
        if self._buffers is None:
            self._buffers = _Buffers(self.shape, self._excite, self._inhibit, self._layer_cos, self._layer_sin)
        return self._buffers

    # ------------------------------------------------------------- dynamics
    def step_attractor(self) -> None:
        """Run excite, inhibit, global inhibition and normalisation (OpenRatSLAM ``on_odo`` steps 1–4).

        Eq. 3 of Menezes et al.: ΔP = Σ P·ε − φ, then P is clipped at 0 and
        normalised to total activity 1. Excitation spreads every cell through the
        ``pc_w_e_dim``-cube Gaussian (σ = ``pc_w_e_var``), wrapping across every face;
        inhibition subtracts the ``pc_w_i_dim``-cube spread of the excited activity.
        Both cubes are separable, so each is applied as one wrapped 1-D spread per axis
        (x, y, [z,] θ in turn; equal to OpenRatSLAM's cell-by-cell spread up to rounding).
        Like OpenRatSLAM, which visits only active cells, the compiled path computes only
        the slices the spreads reach from the active ones; every other cell ends at
        max(0 − φ, 0) = 0, as on the reference path.
        """
        if kernels.enabled():
            self._attractor_compiled()
            return
        cells, total = attractor_reference(self.activity, self._excite, self._inhibit, self.params.pc_global_inhib)
        self.activity = cells
        if not total > 0.0:
            self._restart(cells)

    def _attractor_compiled(self) -> None:
        """Run the attractor step on the compiled path (the restart included)."""
        b = self._compiled()
        out, _ = kernels.kernel("attractor")(
            b.pool, b.dirty, b.slot_of(self.activity), b.dims, b.masks, *b.excite, *b.inhibit,
            self.params.pc_global_inhib, self.best,
        )  # fmt: skip
        self.activity = b.views[out]

    def _restart(self, cells: FloatArray) -> None:
        """Everything was inhibited (OpenRatSLAM asserts): restart from one cell at the decoded packet centre."""
        cells[...] = 0.0
        cells[tuple(int(b) % d for b, d in zip(self.best, self.shape, strict=True))] = 1.0

    def motion(self, forward_m: float, dyaw_rad: float, dz_m: float = 0.0) -> Move | None:
        """Return the path integration of one frame's odometry, or None when nothing moves.

        Heading layer θ_k = k·2π/n_θ moves ``forward/pc_cell_x_size`` cells along (cos θ_k, sin θ_k): ``s`` cells
        along an axis split between the shifts ⌊s⌋ (weight 1 − frac) and ⌊s⌋ + 1 (weight frac); with
        part ``translation`` between 0 and ±1 (OpenRatSLAM's four-neighbour weights, 1 − |s| and |s|, whatever
        |s|). z moves ``dz/pc_cell_z_size`` cells and θ ``dyaw/(2π/n_θ)`` cells, each split between its floor and
        ceiling shifts.
        """
        p = self.params
        v = forward_m / p.pc_cell_x_size
        moved_z = self.rank == 4 and dz_m != 0.0
        if v == 0.0 and dyaw_rad == 0.0 and not moved_z:
            return None
        one_cell = p.follows_openratslam(Departure.TRANSLATION)
        corners = _NO_CORNERS
        if one_cell and v != 0.0 and self.rank == 3:
            corners = _openratslam_corners(self.shape[0], self.shape[-1], v)
        z = _axis_shift(dz_m / p.pc_cell_z_size) if moved_z else _NO_SHIFT
        th = _axis_shift(dyaw_rad / (2.0 * math.pi / self.shape[-1])) if dyaw_rad != 0.0 else _NO_SHIFT
        return Move(v, one_cell, corners, z, th)

    def path_integrate(self, forward_m: float, dyaw_rad: float, dz_m: float = 0.0) -> None:
        """Shift the packet by odometry (OpenRatSLAM ``path_integration``; PoseidonSLAM Eq. 4.17).

        Each heading layer θ_k = k·2π/n_θ is translated by ``forward/pc_cell_x_size``
        cells along (cos θ_k, sin θ_k) with bilinear weights: x then y, each split
        between the two nearest integer shifts (:meth:`motion`). For moves under one cell
        these are OpenRatSLAM's four-neighbour weights (sw, se, nw, ne); larger moves, which
        OpenRatSLAM does not support (its weights turn negative), stay exact here.
        A negative forward motion moves against the layer heading (OpenRatSLAM adds π).
        Then z is shifted by ``dz/pc_cell_z_size`` cells and θ by ``dyaw/(2π/n_θ)``
        cells, each with linear weights between the floor and ceiling shifts (as
        OpenRatSLAM's θ shift). Every shift wraps across the lattice faces.
        """
        move = self.motion(forward_m, dyaw_rad, dz_m)
        if move is None:
            return
        if not kernels.enabled():
            self.activity = path_reference(self.activity, move, self._layer_cos, self._layer_sin)
            return
        b = self._compiled()
        out = kernels.kernel("path_integrate")(
            b.pool, b.dirty, b.slot_of(self.activity), b.dims, b.masks, b.rows, False, move.v, b.cos, b.sin,
            move.one_cell, move.corners, move.z, move.th,
        )  # fmt: skip
        self.activity = b.views[out]

    def decode(self) -> FloatArray:
        """Return the packet centre by population vector around the peak (OpenRatSLAM ``find_best``).

        The peak is the first maximum in OpenRatSLAM's scan order (θ outermost, x
        innermost). Its ±``pc_cells_to_avg`` wrapped window (narrowed on axes too
        short for it, so no cell counts twice) is summed per axis and each axis
        decoded as the circular mean ``atan2(Σ s·sin, Σ s·cos)·n/(2π)`` in [0, n).
        """
        if kernels.enabled():
            b = self._compiled()
            cells = b.rows_view(self.activity)
            kernels.kernel("_occupancy")(cells, b.dims, b.masks[0], np.zeros(cells.shape[0], dtype=np.bool_))
            return self._decode_at(b.peak(cells, self.params.follows_openratslam(Departure.DECODE)))
        return self._decode_at(self._peak_reference())

    def _peak_reference(self) -> list[int]:
        """Return the first maximum's cell: θ outermost, then (z,) y, x; OpenRatSLAM's (``decode``): θ, x, y, (z)."""
        if self.params.follows_openratslam(Departure.DECODE):
            scan = (self.rank - 1, *range(self.rank - 1))
        else:
            scan = tuple(range(self.rank))[::-1]
        flat = int(np.argmax(self.activity.transpose(scan)))
        peak = [0] * self.rank
        for axis, index in zip(scan, np.unravel_index(flat, [self.shape[a] for a in scan]), strict=True):
            peak[axis] = int(index)
        return peak

    def _decode_at(self, peak: list[int]) -> FloatArray:
        """Decode the packet centre around ``peak`` (see :meth:`decode`)."""
        if self.params.follows_openratslam(Departure.DECODE):
            return self._decode_openratslam(peak)
        cells = self.activity
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

    def _decode_openratslam(self, peak: list[int]) -> FloatArray:
        """``find_best`` as OpenRatSLAM's code computes it, to the last bit where it can (part ``decode``).

        OpenRatSLAM's lattice is ours transposed in x and y (its heading-0 layer moves along its second
        axis), so its scan order is (θ, x, y) in ours. Its per-axis sums add cells in its loop order,
        its lookups are (i+1)-based with a final "− 1", and its wrap leaves values in [0, n]. These
        change the decoded centre by ~1e-15 of a cell, but that decides the cell a new template's link
        truncates to (16.999999999999996 → 16, not 17).
        """
        cells = self.activity
        scan = (self.rank - 1, *range(self.rank - 1))
        windows = [(c + off) % d for c, off, d in zip(peak, self._window_offsets, self.shape, strict=True)]
        box = cells[np.ix_(*windows)]
        best = np.empty(self.rank, dtype=np.float64)
        compiled = kernels.enabled()
        for axis in range(self.rank):
            order = [a for a in scan if a != axis]
            flat = np.ascontiguousarray(box.transpose((*order, axis))).reshape(-1, box.shape[axis])
            dim = self.shape[axis]
            if compiled:
                sine_table, cosine_table = _openratslam_tables(dim)
                best[axis] = kernels.kernel("openratslam_axis_centre")(flat, windows[axis], sine_table, cosine_table)
                continue
            marginal = flat.sum(axis=0)
            sines, cosines = _openratslam_lookups(dim)
            weights = marginal.tolist()
            index = windows[axis].tolist()
            s = c = 0.0
            for k in sorted(range(len(index)), key=index.__getitem__):  # index order, as its loop over the axis
                s += sines[index[k]] * weights[k]
                c += cosines[index[k]] * weights[k]
            value = math.atan2(s, c) * dim / (2.0 * math.pi) - 1.0
            while value < 0.0:
                value += dim
            while value > dim:
                value -= dim
            best[axis] = value
        self.best = best
        return best

    def on_odo(self, forward_m: float, dyaw_rad: float, dz_m: float = 0.0) -> FloatArray:
        """Run one OpenRatSLAM ``on_odo`` update and return the decoded packet centre.

        The attractor step, path integration (:meth:`motion`) and the peak search run in one call on the
        compiled path once its kernels are loaded (this network loads them when its updates reach
        ``COMPILED_AFTER`` cell updates).
        """
        self.updates += 1
        if not kernels.enabled() and worth_compiling(self.shape, self.updates):
            kernels.load_compiled()
        if not kernels.enabled():
            self.step_attractor()
            self.path_integrate(forward_m, dyaw_rad, dz_m)
            return self.decode()
        b = self._compiled()
        move = self.motion(forward_m, dyaw_rad, dz_m) or _STILL
        slot, peak = kernels.kernel("on_odo")(
            b.pool, b.dirty, b.slot_of(self.activity), b.dims, b.masks, b.rows, *b.excite, *b.inhibit,
            self.params.pc_global_inhib, self.best, move.v, b.cos, b.sin, move.one_cell, move.corners, move.z,
            move.th, self.params.follows_openratslam(Departure.DECODE),
        )  # fmt: skip
        self.activity = b.views[slot]
        return self._decode_at(b.lattice_peak(peak))

    def inject(self, coords: FloatArray, energy: float) -> None:
        """Add ``energy`` to the cell at ``coords`` truncated to integers (OpenRatSLAM ``inject``)."""
        cell = tuple(int(c) % d for c, d in zip(coords, self.shape, strict=True))
        self.activity[cell] += energy

    # ------------------------------------------------------------ view links
    @property
    def link_count(self) -> int:
        """Return the number of LVC→pose-cell links."""
        return len(self._links_template)

    def add_link(self, template: int, coords: FloatArray, strength: float = 1.0, decay: float | None = None) -> int:
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

    def delta_to(self, coords: FloatArray) -> FloatArray | np.float64:
        """Return wrapped lattice distances from the heading-corrected packet centre to ``coords`` (…, D).

        OpenRatSLAM ``get_delta_pc``: the current θ is corrected by the view's
        relative heading before the wrapped Euclidean distance is taken.
        """
        best = self.best.copy()
        best[-1] = (best[-1] - self.vt_delta_th) % self.shape[-1]
        if np.ndim(coords) == 1:  # one cell (every frame): the same operations on Python floats
            return np.float64(_wrapped_norm(best.tolist(), np.asarray(coords, dtype=np.float64).tolist(), self.shape))
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




class _Buffers:
    """The compiled path's memory: three lattice-sized slots (rows × n_θ), slice masks, the taps as arrays.

    The activity is one of the slots after every compiled step; each step writes others (see
    :func:`core._posecell_kernel.attractor`), so a slot that is not the current activity holds nothing of use.
    """

    SLOTS = 3

    def __init__(
        self, shape: tuple[int, ...], excite: list[Taps], inhibit: list[Taps], cos: FloatArray, sin: FloatArray
    ) -> None:
        self.shape = shape
        self.cos, self.sin = np.ascontiguousarray(cos), np.ascontiguousarray(sin)
        th_dim = shape[-1]
        dims = (shape[0], shape[1], shape[2] if len(shape) == 4 else 1)
        self.dims = np.asarray(dims, dtype=np.int64)
        self.pool = np.zeros((self.SLOTS, math.prod(dims), th_dim), dtype=np.float64)
        self.dirty = np.zeros((self.SLOTS, math.prod(dims)), dtype=np.bool_)
        """Per slot, the rows that may hold a non-zero (every other row is 0)."""
        self.views = [slot.reshape(shape) for slot in self.pool]
        self.masks = np.zeros((4, 4, max(*dims, th_dim)), dtype=np.bool_)
        self.rows = np.zeros(math.prod(dims), dtype=np.int64)
        self.excite = _tap_arrays(excite, shape)
        self.inhibit = _tap_arrays(inhibit, shape)

    def slot_of(self, activity: FloatArray) -> int:
        """Return the slot holding ``activity``, copying it into slot 0 when it is held elsewhere.

        An activity held elsewhere was set from outside (a restore, a test), which may have written into the
        slots too: every row of every slot is then taken as possibly non-zero.
        """
        for slot, view in enumerate(self.views):
            if activity is view:
                return slot
        np.copyto(self.views[0], activity)
        self.dirty[...] = True
        return 0

    def rows_view(self, activity: FloatArray) -> FloatArray:
        """Return ``activity`` as the kernels' (rows, n_θ) array (a view when it is C-contiguous)."""
        return np.ascontiguousarray(activity, dtype=np.float64).reshape(self.pool.shape[1:])

    def peak(self, cells: FloatArray, openratslam_order: bool) -> list[int]:
        """Return the first maximum's cell of ``cells`` (its slices in masks[0]) in the lattice's axes."""
        return self.lattice_peak(kernels.kernel("peak")(cells, self.dims, self.masks[0], openratslam_order))

    def lattice_peak(self, peak: IntArray) -> list[int]:
        """Return a kernel's (x, y, z, θ) cell in the lattice's axes (no z on the 3-DoF lattice)."""
        x, y, z, t = peak.tolist()
        return [x, y, z, t] if len(self.shape) == 4 else [x, y, t]


def _taps(matrix: FloatArray) -> Taps:
    """Return the taps of a circulant matrix ``C[i, j] = k[(i − j) mod d]``: the offsets o with k[o] ≠ 0, and k[o]."""
    column = matrix[:, 0]
    offsets = np.flatnonzero(column)
    return offsets, column[offsets]


def _tap_arrays(taps: list[Taps], shape: tuple[int, ...]) -> tuple[IntArray, FloatArray, IntArray]:
    """Return one kernel's taps as the compiled path takes them: (signed offsets, weights, counts).

    Offsets and weights are (4, K) with rows x, y, z, θ (a 3-DoF lattice has no z taps), in the taps' order;
    each offset o_k (mod n) is written in (−n/2, n/2]. counts (4,) says how many of a row are taps.
    """
    dims = [shape[0], shape[1], shape[2] if len(shape) == 4 else 1, shape[-1]]
    axes = [taps[0], taps[1], taps[2] if len(taps) == 4 else (np.zeros(0, np.int64), np.zeros(0)), taps[-1]]
    width = max(offsets.size for offsets, _ in axes)
    signed = np.zeros((4, width), dtype=np.int64)
    weights = np.zeros((4, width), dtype=np.float64)
    for row, ((o, w), dim) in enumerate(zip(axes, dims, strict=True)):
        o = o.astype(np.int64)
        signed[row, : o.size] = np.where(o > dim // 2, o - dim, o)
        weights[row, : w.size] = w
    counts = np.asarray([o.size for o, _ in axes], dtype=np.int64)
    return signed, weights, counts


def spread_reference(cells: FloatArray, taps: list[Taps]) -> FloatArray:
    """Apply a separable wrapped kernel: along each axis in turn, ``Σ_k w_k·roll(cells, o_k)`` in tap order."""
    for axis, (offsets, weights) in enumerate(taps):
        acc = np.zeros_like(cells)
        for o, w in zip(offsets.tolist(), weights.tolist(), strict=True):
            acc += w * np.roll(cells, o, axis=axis)
        cells = acc
    return cells


def attractor_reference(
    cells: FloatArray, excite: list[Taps], inhibit: list[Taps], inhibition: float
) -> tuple[FloatArray, float]:
    """Return the attractor step of ``cells`` and its pre-scale total (Menezes et al. Eq. 3; the reference path).

    ``max(E − I − φ, 0)`` with E the excitatory spread and I the inhibitory spread of E, scaled to sum 1 when
    the total is positive. The total adds the cells in C order, one after another (the compiled path's order).
    """
    excited = spread_reference(np.asarray(cells, dtype=np.float64), excite)
    out = excited - spread_reference(excited, inhibit)
    out -= inhibition
    np.maximum(out, 0.0, out=out)
    total = float(np.add.accumulate(out.ravel())[-1])
    if total > 0.0:
        out /= total
    return out, total


def path_reference(activity: FloatArray, move: Move, cos: FloatArray, sin: FloatArray) -> FloatArray:
    """Return ``activity`` moved by one frame's path integration (the reference path; see :class:`Move`)."""
    cells = np.moveaxis(np.asarray(activity, dtype=np.float64), -1, 0).copy()  # heading first: (θ, x, y, [z])
    th_dim = cells.shape[0]
    if move.v != 0.0:
        layers = np.flatnonzero(cells.reshape(th_dim, -1).any(axis=1))
        before = cells[layers]
        cells[layers] = _translate_layers(before, layer_moves(move.v, cos, sin, move.one_cell)[layers])
        if move.corners.shape[0]:
            _lose_corners(cells, before, layers, move.corners)
    if move.z[0] != 0.0:
        cells = _shift_axis(cells, int(move.z[1]), float(move.z[2]), float(move.z[3]), 3)
    if move.th[0] != 0.0:
        cells = _shift_axis(cells, int(move.th[1]), float(move.th[2]), float(move.th[3]), 0)
    return np.ascontiguousarray(np.moveaxis(cells, 0, -1))


def _lose_corners(cells: FloatArray, before: FloatArray, layers: IntArray, corners: FloatArray) -> None:
    """Subtract OpenRatSLAM's translation loss of each moved layer (:func:`_openratslam_corners`), heading first."""
    for plane, k in zip(before, layers.tolist(), strict=True):
        a, w_a, b, w_b, to = corners[k]
        lost = plane.flat[int(a)] * w_a + plane.flat[int(b)] * w_b
        if lost != 0.0:
            cells[k].flat[int(to)] -= lost


def layer_moves(v: float, cos: FloatArray, sin: FloatArray, one_cell: bool) -> FloatArray:
    """Return (n_θ, 6) per heading layer: (whole_x, keep_x, frac_x, whole_y, keep_y, frac_y) of a move by ``v`` cells.

    Layer t moves ``v·cos_t`` cells along x and ``v·sin_t`` along y (:func:`_shift_weights`; keep = 1 − frac).
    """
    whole_x, frac_x = _shift_weights(v * cos, one_cell)
    whole_y, frac_y = _shift_weights(v * sin, one_cell)
    return np.stack([whole_x, 1.0 - frac_x, frac_x, whole_y, 1.0 - frac_y, frac_y], axis=1)


def _translate_layers(layers: FloatArray, moves: FloatArray) -> FloatArray:
    """Move each (x, y, [z]) plane of ``layers`` x then y: ``keep·P[i − whole] + frac·P[i − whole − 1]`` per axis."""
    out = layers
    for axis, (whole, keep, frac) in ((1, moves[:, 0:3].T), (2, moves[:, 3:6].T)):
        dim = out.shape[axis]
        near = (np.arange(dim)[None, :] - whole.astype(np.int64)[:, None]) % dim
        shape = [near.shape[0], 1, 1] + [1] * (out.ndim - 3)
        shape[axis] = dim
        first = np.take_along_axis(out, near.reshape(shape), axis=axis)
        second = np.take_along_axis(out, ((near - 1) % dim).reshape(shape), axis=axis)
        weight = (slice(None),) + (None,) * (out.ndim - 1)
        out = keep[weight] * first + frac[weight] * second
    return out


def _shift_weights(shifts: FloatArray, one_cell: bool = False) -> tuple[FloatArray, FloatArray]:
    """Return (whole, frac) of moves of ``shifts`` cells: cell i goes to ``i + whole`` (1 − frac) and ``i + whole + 1``.

    ``whole = ⌊s⌋``; with ``one_cell`` (OpenRatSLAM's four-neighbour weights, the same for |s| ≤ 1) ``whole`` is
    0 or −1 whatever the size of ``s``, so cell i keeps ``1 − |s|`` and sends ``|s|`` one cell.
    """
    whole = np.where(shifts >= 0.0, 0.0, -1.0) if one_cell else np.floor(shifts)
    return whole, shifts - whole


def _axis_shift(shift: float) -> FloatArray:
    """Return (1, whole, keep, frac) of a shift along z or θ by ``shift`` cells: floor and ceiling, linear weights."""
    whole = math.floor(shift)
    frac = shift - whole
    return np.asarray([1.0, whole, 1.0 - frac, frac])


@functools.lru_cache(maxsize=64)
def _openratslam_rot90(dim: int, rot: int) -> IntArray:
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




def _wrapped_norm(a: list[float], b: list[float], dims: tuple[int, ...]) -> float:
    """Return :func:`core.lattice.wrapped_distance` of two cells to the last bit (its operations, in its order).

    Per axis ``d = |a − b| mod n`` (exact, as numpy's mod of a non-negative number), ``min(d, n − d)``; the
    squares summed from the first axis on, as numpy sums a short axis; then the square root.
    """
    total = 0.0
    for x, y, dim in zip(a, b, dims, strict=True):
        d = math.fmod(abs(x - y), dim)
        d = min(d, dim - d)
        total += d * d
    return math.sqrt(total)


@functools.lru_cache(maxsize=16)
def _openratslam_lookups(dim: int) -> tuple[list[float], list[float]]:
    """Return OpenRatSLAM's (i+1)-based sine and cosine tables of one axis: ``sin((i + 1)·2π/dim)``, i < dim."""
    angles = [(i + 1) * 2.0 * math.pi / dim for i in range(dim)]
    return [math.sin(a) for a in angles], [math.cos(a) for a in angles]


@functools.lru_cache(maxsize=16)
def _openratslam_tables(dim: int) -> tuple[FloatArray, FloatArray]:
    """Return :func:`_openratslam_lookups` as read-only arrays, for the compiled decoding."""
    sines, cosines = (np.array(table, dtype=np.float64) for table in _openratslam_lookups(dim))
    sines.setflags(write=False)
    cosines.setflags(write=False)
    return sines, cosines


def _openratslam_corners(dim: int, th_dim: int, v: float) -> FloatArray:
    """Return per heading layer what OpenRatSLAM's translation loses at its rotated corner (part ``translation``).

    OpenRatSLAM rotates layer k by ⌊2·dir/π⌋ quarter turns (dir = k·2π/n_θ, + π when moving backwards),
    moves it by at most one cell towards +i and +j on a plane padded by one cell, then wraps the padding
    back — but its two wrap-back loops start at index 1, so what leaves rotated cell (0, n−1) along +i
    (weight ``v·sin·(1 − v·cos)``) and rotated cell (n−1, 0) along +j (weight ``v·cos·(1 − v·sin)``) never
    reaches rotated cell (0, 0). Row k = (cell a, its weight, cell b, its weight, cell losing it): flat indices
    into layer k's (x, y) plane before the move (a, b) and after it (the loser); our x is its j.
    """
    speed = abs(v)
    corners = np.zeros((th_dim, 5))
    for k, (sin90, cos90, cells) in enumerate(_corner_layers(dim, th_dim, v < 0)):
        along_i = speed * sin90 * (1.0 - speed * cos90)
        along_j = speed * cos90 * (1.0 - speed * sin90)
        corners[k] = (cells[0], along_i, cells[1], along_j, cells[2])
    return corners


@functools.lru_cache(maxsize=64)
def _corner_layers(dim: int, th_dim: int, backwards: bool) -> tuple[tuple[float, float, tuple[int, int, int]], ...]:
    """Return per heading layer (sin, cos of its direction within its quarter turn, its three corner cells).

    What :func:`_openratslam_corners` needs that does not depend on the speed, computed once per lattice and
    direction of travel (the rotation of an index grid is pure Python).
    """
    extra = math.pi if backwards else 0.0
    layers = []
    for k in range(th_dim):
        direction = k * (2.0 * math.pi / th_dim) + extra
        quarter = math.floor(direction * 2 / math.pi)
        dir90 = direction - quarter * math.pi / 2
        where = _openratslam_rot90(dim, int(quarter) % 4)
        cells = (int(where[0, dim - 1]), int(where[dim - 1, 0]), int(where[0, 0]))
        layers.append((math.sin(dir90), math.cos(dir90), cells))
    return tuple(layers)


def _shift_axis(cells: FloatArray, whole: int, keep: float, frac: float, axis: int) -> FloatArray:
    """Return ``cells`` shifted along ``axis`` (wrapping): ``P[k − whole]·keep + P[k − whole − 1]·frac``.

    OpenRatSLAM's θ shift with ``whole = ⌊s⌋``, ``frac = s − ⌊s⌋``, ``keep = 1 − frac``.
    """
    out = np.roll(cells, whole, axis=axis)
    if frac == 0.0:
        return out
    spare = np.roll(cells, whole + 1, axis=axis)
    out *= keep
    spare *= frac
    out += spare
    return out

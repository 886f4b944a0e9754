"""Pose cells: a continuous attractor network on a wrapping (x, y, [z,] θ) lattice.

Implements OpenRatSLAM's ``PosecellNetwork`` (Ball et al. 2013; anchors §1.1) in
the RatSLAM notation of Menezes et al. (2023) §2.1–2.2, generalised to the 4-DoF
(x, y, z, ψ) lattice of PoseidonSLAM (thesis §4.2.4, Eqs. 4.16–4.19):

* attractor dynamics ``on_odo``: excite (Eq. 1–3 excitatory part), inhibit,
  global inhibition φ, normalise to 1, path integration, population-vector decode;
* the LVC→pose-cell link table β (Eq. 4 / 4.19) with OpenRatSLAM's injection
  saturation ``δ/30·(30 − e^{1.2·decay})`` (Eq. 5).

Array layout is ``activity[x, y, (z,) th]``. Coordinates are in cells.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from core._buffers import GrowBuffer
from core.lattice import periodic_kernel_spectrum, wrapped_distance

if TYPE_CHECKING:
    from core.config import Params


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
        rank = self.rank
        excite = periodic_kernel_spectrum(self.shape, (p.pc_w_e_dim,) * rank, p.pc_w_e_var)
        inhibit = periodic_kernel_spectrum(self.shape, (p.pc_w_i_dim,) * rank, p.pc_w_i_var)
        # excite (P ⊛ W_E) then inhibit (P' − P' ⊛ W_I) is one linear operator:
        # F⁻¹(F(P)·Ŵ_E·(1 − Ŵ_I)).
        self._dynamics_spectrum = excite * (1.0 - inhibit)
        self._axis_index = [np.arange(d) for d in self.shape]
        self._all_axes = tuple(range(self.rank))
        th_dim = self.shape[-1]
        angles = np.arange(th_dim, dtype=np.float64) * (2.0 * math.pi / th_dim)
        # exact zeros on the axis-aligned layers, so integer moves stay integer
        self._layer_cos = np.where(np.abs(np.cos(angles)) < 1e-12, 0.0, np.cos(angles))
        self._layer_sin = np.where(np.abs(np.sin(angles)) < 1e-12, 0.0, np.sin(angles))
        # Population-vector decoding lookups (OpenRatSLAM find_best).
        self._sin_lookup = [np.sin(np.arange(d) * 2.0 * math.pi / d) for d in self.shape]
        self._cos_lookup = [np.cos(np.arange(d) * 2.0 * math.pi / d) for d in self.shape]
        radius = int(p.pc_cells_to_avg)
        self._window_offsets = [np.arange(-min(radius, (d - 1) // 2), min(radius, (d - 1) // 2) + 1)
                                for d in self.shape]

    # ------------------------------------------------------------- dynamics
    def step_attractor(self) -> None:
        """Run excite, inhibit, global inhibition and normalisation (OpenRatSLAM ``on_odo`` steps 1–4).

        Eq. 3 of Menezes et al.: ΔP = Σ P·ε − φ, then P is clipped at 0 and
        normalised to total activity 1. The wrapped convolutions are evaluated in
        the frequency domain, which equals the cell-by-cell sum up to rounding.
        """
        p = self.params
        spectrum = np.fft.rfftn(self.activity)
        cells = np.fft.irfftn(spectrum * self._dynamics_spectrum, s=self.shape, axes=self._all_axes)
        cells -= p.pc_global_inhib
        np.maximum(cells, 0.0, out=cells)
        total = cells.sum()
        if total > 0.0:
            cells /= total
        else:  # everything inhibited: restart from the decoded packet centre
            cells[...] = 0.0
            cells[tuple(int(b) % d for b, d in zip(self.best, self.shape, strict=True))] = 1.0
        self.activity = cells

    def path_integrate(self, forward_m: float, dyaw_rad: float, dz_m: float = 0.0) -> None:
        """Shift the packet by odometry (OpenRatSLAM ``path_integration``).

        Each heading layer θ_k = k·2π/n_θ is translated by ``forward/pc_cell_x_size``
        cells along (cos θ_k, sin θ_k) with bilinear weights (the four-neighbour
        weights of OpenRatSLAM, generalised to shifts of more than one cell);
        z is shifted by ``dz/pc_cell_z_size`` cells and θ by ``dyaw/(2π/n_θ)`` cells,
        both with linear interpolation between the two nearest integer shifts.
        Every shift wraps across the lattice faces.
        """
        p = self.params
        cells = self.activity
        v = forward_m / p.pc_cell_x_size
        if v != 0.0:
            sx = v * self._layer_cos
            sy = v * self._layer_sin
            cells = self._shift_layers(cells, sx, axis=0)
            cells = self._shift_layers(cells, sy, axis=1)
        if self.rank == 4 and dz_m != 0.0:
            cells = _shift_axis(cells, dz_m / p.pc_cell_z_size, axis=2)
        th_dim = self.shape[-1]
        if dyaw_rad != 0.0:
            cells = _shift_axis(cells, dyaw_rad / (2.0 * math.pi / th_dim), axis=self.rank - 1)
        self.activity = cells

    def _shift_layers(self, cells: np.ndarray, shifts: np.ndarray, axis: int) -> np.ndarray:
        """Shift every θ layer along ``axis`` by its own fractional amount ``shifts[k]`` (cells)."""
        dim = self.shape[axis]
        whole = np.floor(shifts)
        frac = shifts - whole
        idx = self._axis_index[axis]
        src0 = (idx[:, None] - whole[None, :].astype(np.int64)) % dim  # (dim, n_th)
        src1 = (src0 - 1) % dim
        th = self._axis_index[-1]
        # Gather cells[src, ..., k] for every layer k with broadcasting.
        index0: list[np.ndarray] = []
        index1: list[np.ndarray] = []
        for a in range(self.rank):
            shape = [1] * self.rank
            if a == axis:
                shape[a] = dim
                shape[-1] = self.shape[-1]
                index0.append(src0.reshape(shape))
                index1.append(src1.reshape(shape))
            elif a == self.rank - 1:
                shape[a] = self.shape[a]
                index0.append(th.reshape(shape))
                index1.append(th.reshape(shape))
            else:
                shape[a] = self.shape[a]
                index0.append(self._axis_index[a].reshape(shape))
                index1.append(self._axis_index[a].reshape(shape))
        w1 = frac.reshape([1] * (self.rank - 1) + [self.shape[-1]])
        return (1.0 - w1) * cells[tuple(index0)] + w1 * cells[tuple(index1)]

    def decode(self) -> np.ndarray:
        """Return the packet centre by population vector around the peak (OpenRatSLAM ``find_best``).

        The argmax cell's ±``pc_cells_to_avg`` wrapped window is summed per axis and
        each axis decoded as the circular mean ``atan2(Σ s·sin, Σ s·cos)·n/(2π)``.
        """
        cells = self.activity
        peak = np.unravel_index(int(np.argmax(cells)), self.shape)
        windows = [(int(c) + off) % d for c, off, d in zip(peak, self._window_offsets, self.shape, strict=True)]
        box = cells[np.ix_(*windows)]
        best = np.empty(self.rank, dtype=np.float64)
        all_axes = tuple(range(self.rank))
        for axis in range(self.rank):
            marginal = box.sum(axis=tuple(a for a in all_axes if a != axis))
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

        A new template is linked to the current packet centre. A known template
        older than ``vt_min_inject_age`` creations injects, through each of its
        links, ``pc_vt_inject_energy·strength/30·(30 − e^{1.2·decay})`` at the link
        cell with θ offset by the view's ``relative_rad``; seeing the same template
        again raises its decay by ``vt_active_decay`` (saturation). Every link's
        decay then relaxes by ``pc_vt_restore`` down to ``vt_active_decay``.
        """
        p = self.params
        th_dim = self.shape[-1]
        self.vt_delta_th = relative_rad / (2.0 * math.pi) * th_dim
        if created:
            self.add_link(template, self.best.copy())
        elif template < template_count - p.vt_min_inject_age:
            decay = self._links_decay.view
            coords_all = self._links_coords.view
            strength = self._links_strength.view
            for link in self.links_of(template):
                if template == self.current_vt:
                    decay[link] += p.vt_active_decay
                energy = p.pc_vt_inject_energy * strength[link] / 30.0 * (30.0 - math.exp(1.2 * decay[link]))
                if energy > 0.0:
                    coords = coords_all[link].copy()
                    coords[-1] = (coords[-1] + self.vt_delta_th) % th_dim
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


def _shift_axis(cells: np.ndarray, shift: float, axis: int) -> np.ndarray:
    """Shift ``cells`` along ``axis`` by a fractional number of cells, wrapping, with linear weights."""
    whole = math.floor(shift)
    frac = shift - whole
    shifted = np.roll(cells, whole, axis=axis)
    if frac == 0.0:
        return shifted
    return (1.0 - frac) * shifted + frac * np.roll(shifted, 1, axis=axis)

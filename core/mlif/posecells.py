"""PC-MLIF pose cells behind the engine's pose-cell interface (``pc_model = mlif``; Pirozzo et al. 2024).

Two spiking networks (:class:`core.mlif.network.MlifNetwork`) replace the CAN lattice of
:class:`core.posecells.PoseCellNetwork`:

* the **position** network (x, y, z), ``pc_dim_xy² × pc_dim_z`` cells (one z cell for the 3-DoF engine), moved
  by the linear velocity along the decoded heading and by the vertical velocity;
* the **heading** network (x, y, θ), ``pc_dim_xy² × pc_dim_th`` cells, each θ layer moved along its own heading
  and all layers by the angular velocity (the CAN's path integration, Eqs 9–12).

Their codes (:attr:`MlifPoseCells.best`) are the CAN's: (x, y, [z,] θ) in cells — x, y (and z) decoded from the
position network, θ from the heading network — so the experience map, its decisions (``delta_to``) and its
stored lattice codes are those of the CAN engine of the same rank.

Local-view calibration (Eq. 13, ``ψ ← max(ψ, ξ·V_i·P)``): with one active view cell (V one-hot) and ξ = 1 the
link's largest weight sits at the packet's peak, so a link stores that cell in both networks (the decoded
centres, as the CAN's links) and a known view injects there ([A] Eq. 4) with the CAN's saturation and age rules
(``pc_vt_inject_energy``, ``vt_active_decay``, ``pc_vt_restore``, ``vt_min_inject_age``; see
:meth:`core.posecells.PoseCellNetwork.on_view_template`), the heading network's θ offset by the view's relative
heading. Kernels reuse ``pc_w_e_*``/``pc_w_i_*``, the decoding window ``pc_cells_to_avg``; the neuron, memristor
and network constants are in :mod:`core.mlif.neuron` and :mod:`core.mlif.network`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import TYPE_CHECKING

import numpy as np
import torch

from core.config import Departure
from core.lattice import wrapped_distance
from core.mlif.network import KernelSpec, MlifNetwork

if TYPE_CHECKING:
    from core.config import Params


@contextmanager
def one_thread() -> Iterator[None]:
    """Run torch's CPU operations on one thread inside the block, then restore the thread count.

    The networks' tensors are small (a box around the packet) or cheap passes over the lattice: split over
    threads they ran 6× slower on a loaded 2-core machine (``mapserver process``, 57.6 against 9.1 frames/s on
    the ``loop`` log), and no result depends on the thread count (every sum is exact or elementwise).
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


class MlifPoseCells:
    """The position and heading PC-MLIF networks with their view links, as the engine drives pose cells."""

    def __init__(self, params: Params) -> None:
        self.params = params
        self.shape: tuple[int, ...] = tuple(int(d) for d in params.lattice_shape)
        self.rank = len(self.shape)
        self.dims = np.asarray(self.shape, dtype=np.float64)
        kernels = KernelSpec(params.pc_w_e_dim, params.pc_w_e_var, params.pc_w_i_dim, params.pc_w_i_var)
        n_xy, n_th = params.pc_dim_xy, params.pc_dim_th
        self.position = MlifNetwork((n_xy, n_xy, max(1, params.pc_dim_z)), kernels)
        self.heading = MlifNetwork((n_xy, n_xy, n_th), kernels)
        angles = [k * 2.0 * math.pi / n_th for k in range(n_th)]
        self._cos = [0.0 if abs(math.cos(a)) < 1e-12 else math.cos(a) for a in angles]
        self._sin = [0.0 if abs(math.sin(a)) < 1e-12 else math.sin(a) for a in angles]
        self.best = self._codes()
        self.current_vt = -1
        self.prev_vt = -1
        self.vt_delta_th = 0.0
        self._link_template: list[int] = []
        self._link_cells: list[np.ndarray] = []
        """Per link: position centre (x, y, z) then heading centre (x, y, θ), cells."""
        self._link_decay: list[float] = []
        self._links_of: dict[int, list[int]] = {}

    # ------------------------------------------------------------- dynamics
    def _codes(self) -> np.ndarray:
        """Return (x, y, [z,] θ): the position network's centre and the heading network's θ."""
        radius = int(self.params.pc_cells_to_avg)
        pos = self.position.decode(radius)
        theta = self.heading.decode(radius)[2]
        if self.rank == 4:
            return np.asarray([pos[0], pos[1], pos[2], theta], dtype=np.float64)
        return np.asarray([pos[0], pos[1], theta], dtype=np.float64)

    def on_odo(self, forward_m: float, dyaw_rad: float, dz_m: float = 0.0) -> np.ndarray:
        """Run both networks' attractor step, path-integrate the frame's motion, and return the new codes.

        The position network moves ``forward/pc_cell_x_size`` cells along the heading network's decoded heading
        (after its attractor step, before the turn, as each CAN layer moves along its heading before the θ
        shift) and ``dz/pc_cell_z_size`` cells in z; the heading network as the CAN lattice. torch runs on one
        thread meanwhile (:func:`one_thread`).
        """
        with one_thread():
            return self._on_odo(forward_m, dyaw_rad, dz_m)

    def _on_odo(self, forward_m: float, dyaw_rad: float, dz_m: float) -> np.ndarray:
        p = self.params
        self.position.attract()
        self.heading.attract()
        forward = forward_m / p.pc_cell_x_size
        n_th = self.shape[-1]
        theta = self.heading.decode(int(p.pc_cells_to_avg))[2] * 2.0 * math.pi / n_th
        dz = dz_m / p.pc_cell_z_size if self.rank == 4 else 0.0
        if forward != 0.0 or dz != 0.0:
            self.position.shift((forward * math.cos(theta), forward * math.sin(theta), dz))
        if forward != 0.0 or dyaw_rad != 0.0:
            self.heading.shift_layers(forward, self._cos, self._sin, dyaw_rad / (2.0 * math.pi / n_th))
        self.best = self._codes()
        return self.best

    # ------------------------------------------------------------ view links
    def on_view_template(self, template: int, relative_rad: float, template_count: int, created: bool) -> None:
        """Link a new template to both packets' centres, or let a known one inject (CAN rules; module docstring)."""
        p = self.params
        if created:
            self._add_link(template, self._link_cells_now(), p.vt_active_decay)
        elif template < template_count - p.vt_min_inject_age or (
            template_count < p.vt_min_inject_age and p.follows_openratslam(Departure.INJECTION)
        ):
            self._inject(template, relative_rad)
        self._link_decay = [max(d - p.pc_vt_restore, p.vt_active_decay) for d in self._link_decay]
        self.prev_vt = self.current_vt
        self.current_vt = template

    def _link_cells_now(self) -> np.ndarray:
        radius = int(self.params.pc_cells_to_avg)
        return np.concatenate([self.position.decode(radius), self.heading.decode(radius)])

    def _add_link(self, template: int, cells: np.ndarray, decay: float) -> None:
        self._links_of.setdefault(template, []).append(len(self._link_template))
        self._link_template.append(template)
        self._link_cells.append(cells)
        self._link_decay.append(decay)

    def _inject(self, template: int, relative_rad: float) -> None:
        """Inject ``pc_vt_inject_energy/30·(30 − e^{1.2·decay})`` at each link's cells in both networks."""
        p = self.params
        n_th = self.shape[-1]
        offset = relative_rad / (2.0 * math.pi) * n_th
        for link in self._links_of.get(template, []):
            if template == self.current_vt:
                self._link_decay[link] += p.vt_active_decay
            energy = p.pc_vt_inject_energy / 30.0 * (30.0 - math.exp(min(1.2 * self._link_decay[link], 700.0)))
            if energy > 0.0:
                self.vt_delta_th = offset
                cells = self._link_cells[link]
                self.position.inject((int(cells[0]), int(cells[1]), int(cells[2])), energy)
                self.heading.inject((int(cells[3]), int(cells[4]), int((cells[5] + offset) % n_th)), energy)

    def delta_to(self, coords: np.ndarray) -> np.ndarray | np.float64:
        """Return wrapped cell distances from the heading-corrected codes to ``coords`` (…, rank), as the CAN's."""
        best = self.best.copy()
        best[-1] = (best[-1] - self.vt_delta_th) % self.shape[-1]
        distances = wrapped_distance(best, coords, self.dims)
        return np.float64(distances) if np.ndim(distances) == 0 else distances

    # ------------------------------------------------------------- snapshot
    def snapshot(self) -> dict[str, np.ndarray]:
        """Return both networks (activity, potentials, memristor states), the codes and the links (keys ``ml_*``)."""
        state = {**self.position.snapshot("ml_pos"), **self.heading.snapshot("ml_head")}
        state["ml_best"] = self.best.copy()
        state["ml_vt"] = np.asarray([self.current_vt, self.prev_vt], dtype=np.int64)
        state["ml_vt_delta_th"] = np.asarray(self.vt_delta_th, dtype=np.float64)
        state["ml_link_template"] = np.asarray(self._link_template, dtype=np.int64)
        state["ml_link_cells"] = np.asarray(self._link_cells, dtype=np.float64).reshape(-1, 6)
        state["ml_link_decay"] = np.asarray(self._link_decay, dtype=np.float64)
        return state

    @classmethod
    def restore(cls, params: Params, state: Mapping[str, np.ndarray]) -> MlifPoseCells:
        """Rebuild the pose cells from :meth:`snapshot` arrays, exactly."""
        net = cls(params)
        net.position.load(state, "ml_pos")
        net.heading.load(state, "ml_head")
        net.best = np.asarray(state["ml_best"], dtype=np.float64).copy()
        vt = np.asarray(state["ml_vt"], dtype=np.int64)
        net.current_vt, net.prev_vt = int(vt[0]), int(vt[1])
        net.vt_delta_th = float(state["ml_vt_delta_th"])
        cells = np.asarray(state["ml_link_cells"], dtype=np.float64).reshape(-1, 6)
        decays = np.asarray(state["ml_link_decay"], dtype=np.float64).tolist()
        for template, row, decay in zip(np.asarray(state["ml_link_template"]).tolist(), cells, decays, strict=True):
            net._add_link(int(template), row.copy(), float(decay))
        return net

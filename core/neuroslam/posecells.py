"""NeuroSLAM's conjunctive pose cells behind the engine's pose-cell interface (``engine = neuroslam``).

The engine (:class:`core.engine.Engine`) asks its pose cells for the same things whichever engine runs: take
this frame's template (:meth:`on_view_template`), move with the frame's motion (:meth:`on_odo`), the packet's
codes (:attr:`best`, here the five of notes ``neuroslam.md`` §7.1: grid x, y, z and head yaw, height, in cells),
and wrapped distances from them (:meth:`delta_to`, the 5-D distance of Eq. 22 with unit weights). The codes an
experience stores are these five, so the experience map keeps a 5-wide lattice code per experience.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from core.lattice import wrapped_distance
from core.neuroslam.attractor import FloatArray
from core.neuroslam.networks import ConjunctivePoseCells, GridCellParams, HeadDirectionParams
from core.neuroslam.viewlinks import ViewDecay, ViewLinks

if TYPE_CHECKING:
    from core.config import Params

CODE_RANK = 5
"""Codes per experience: grid x, y, z and head-direction yaw, height."""


def grid_params(params: Params) -> GridCellParams:
    """The grid-cell network of ``params`` (``gc_*`` keys)."""
    return GridCellParams(
        dims=(params.gc_dim_xy, params.gc_dim_xy, params.gc_dim_z), excite_size=params.gc_excite_size,
        excite_sigma=params.gc_excite_var, inhibit_size=params.gc_inhibit_size, inhibit_sigma=params.gc_inhibit_var,
        global_inhibition=params.gc_global_inhib, inject_energy=params.gc_vt_inject_energy,
        window=params.gc_packet_size, cell_size=params.gc_cell_size, cell_size_z=params.gc_cell_size_z,
    )


def head_params(params: Params) -> HeadDirectionParams:
    """The head-direction network of ``params`` (``hdc_*`` keys)."""
    return HeadDirectionParams(
        dims=(params.hdc_dim_yaw, params.hdc_dim_height), excite_size=params.hdc_excite_size,
        excite_sigma=params.hdc_excite_var, inhibit_size=params.hdc_inhibit_size,
        inhibit_sigma=params.hdc_inhibit_var, global_inhibition=params.hdc_global_inhib,
        inject_energy=params.hdc_vt_inject_energy, window=params.hdc_packet_size,
        cell_size_height=params.hdc_cell_size_height,
    )


class NeuroslamPoseCells:
    """Grid and head-direction cells with their view links, as the engine drives pose cells."""

    rank = CODE_RANK

    def __init__(self, params: Params) -> None:
        self.params = params
        self.cells = ConjunctivePoseCells(grid_params(params), head_params(params))
        self.links = ViewLinks(ViewDecay(active_decay=params.vt_active_decay, global_decay=params.vt_global_decay))
        self.dims = np.asarray((*self.cells.grid_params.dims, *self.cells.head_params.dims), dtype=np.float64)
        self.best: FloatArray = self.cells.codes.as_array()
        self.current_vt = -1
        self.prev_vt = -1

    def on_view_template(self, template: int, relative_rad: float, template_count: int, created: bool) -> None:
        """Take this frame's template: store a new one's codes, or inject a rested, re-entered one's energy.

        ``relative_rad`` and ``template_count`` are not used: NeuroSLAM's views carry no heading offset, and its
        injection rule is the template's own novelty (:mod:`core.neuroslam.viewlinks`).
        """
        self.links.on_view(template, created, self.cells)
        self.prev_vt = self.current_vt
        self.current_vt = template

    def on_odo(self, forward_m: float, dyaw_rad: float, dz_m: float = 0.0) -> FloatArray:
        """Move both networks by the frame's motion (notes §6 steps 4–7) and return the new codes."""
        self.best = self.cells.step(forward_m, dyaw_rad, dz_m).as_array()
        return self.best

    def delta_to(self, coords: FloatArray) -> FloatArray | np.float64:
        """Wrapped 5-D cell distances from the packet's codes to ``coords`` (…, 5)."""
        distances = wrapped_distance(self.best, coords, self.dims)
        return np.float64(distances) if np.ndim(distances) == 0 else distances

    def snapshot(self) -> dict[str, FloatArray]:
        """Both networks, the codes and the view links, as arrays (keys ``ns_*`` and ``nl_*``)."""
        state = self.cells.snapshot()
        state["ns_vt"] = np.asarray([self.current_vt, self.prev_vt], dtype=np.float64)
        state.update(self.links.snapshot())
        return state

    @classmethod
    def restore(cls, params: Params, state: Mapping[str, FloatArray]) -> NeuroslamPoseCells:
        """The pose cells as :meth:`snapshot` saved them."""
        net = cls(params)
        net.cells = ConjunctivePoseCells.restore(state, net.cells.grid_params, net.cells.head_params)
        net.links = ViewLinks.restore(state, net.links.decay_params)
        net.best = net.cells.codes.as_array()
        vt = np.asarray(state["ns_vt"]).astype(np.int64)
        net.current_vt, net.prev_vt = int(vt[0]), int(vt[1])
        return net

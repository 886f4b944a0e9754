"""NeuroSLAM's conjunctive pose cells: a 3-D grid-cell network and a multilayer head-direction network.

Yu et al. (2019) §4.2 split RatSLAM's (x, y, θ) pose cells in two (notes ``neuroslam.md`` §0–2, §6):

* grid cells, a 36 × 36 × 36 wrapping cube coding (x, y, z): 7³ excitation (σ 1.5), 5³ inhibition (σ 2),
  global inhibition φ; path integration moves the packet by ``v cos ψ``, ``v sin ψ`` in the plane and by the
  height rate along z (Eqs. 1–9);
* head-direction cells, a 36 × 36 wrapping sheet coding (yaw, height): 8² excitation (σ 1.9), 5² inhibition
  (σ 3.0), path integration by the yaw rate and the height rate (Eqs. 12–20).

One frame runs as the authors' code does (notes §6), not as the paper's prose orders it: the head-direction
network first (view injection, attractor, shift by yaw and height rate), its decoded yaw then drives the grid
cells' planar shift (the paper's Discussion says the same), then the grid cells (injection, attractor, shift).

Defaults are the paper's SynPerData columns of Tables 5 and 6. Decisions where paper and code leave room:

* **Axes.** Grid axis 0 moves with ``cos ψ`` and axis 1 with ``sin ψ`` (world x, y; the authors' code has them
  the other way round in its arrays and swaps its plot labels).
* **Cell sizes.** Metres per cell are parameters: ``gc_cell_size`` (plane), ``gc_cell_size_z`` and
  ``hdc_cell_size_height`` (1 m per cell in Table 5/6's QUTCarparkData column). The authors' code moves
  height by ``v_h / (2π/36)`` cells, an angle size reused for height; here it is ``v_h / cell size``.
* **View calibration** injects into one cell of each network, at the codes a template stored when it was made,
  with OpenRatSLAM's saturation ``δ (30 − e^{1.2·decay}) / 30`` (the code's form of Eqs. 10–11; notes §1.5).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from core.lattice import wrapped_distance
from core.neuroslam.attractor import FloatArray, Kernel, WrappedAttractor

INJECTION_SATURATION = 30.0
"""OpenRatSLAM's injection saturation: energy ``δ (30 − e^{1.2·decay}) / 30`` (notes §1.5)."""


@dataclass(frozen=True)
class GridCellParams:
    """Table 5 (SynPerData): the 3-D grid-cell network."""

    dims: tuple[int, int, int] = (36, 36, 36)
    excite_size: int = 7
    excite_sigma: float = 1.5
    inhibit_size: int = 5
    inhibit_sigma: float = 2.0
    global_inhibition: float = 0.0002
    inject_energy: float = 0.1
    window: int = 4
    cell_size: float = 1.0
    cell_size_z: float = 1.0


@dataclass(frozen=True)
class HeadDirectionParams:
    """Table 6 (SynPerData): the multilayer (yaw × height) head-direction network."""

    dims: tuple[int, int] = (36, 36)
    excite_size: int = 8
    excite_sigma: float = 1.9
    inhibit_size: int = 5
    inhibit_sigma: float = 3.0
    global_inhibition: float = 0.0002
    inject_energy: float = 0.001
    window: int = 5
    cell_size_height: float = 1.0


@dataclass(frozen=True)
class Codes:
    """Where the two packets sit, in fractional cells: grid (x, y, z) and head direction (yaw, height)."""

    grid: tuple[float, float, float]
    head: tuple[float, float]

    def as_array(self) -> FloatArray:
        """The five codes in order x, y, z, yaw, height (the experience map's 5-D cell space, notes §7.1)."""
        return np.array([*self.grid, *self.head], dtype=np.float64)


def injection_energy(strength: float, decay: float) -> float:
    """``δ (30 − e^{1.2·decay}) / 30``, floored at 0: a template seen often in a row stops injecting."""
    energy = strength * (INJECTION_SATURATION - math.exp(1.2 * decay)) / INJECTION_SATURATION
    return max(energy, 0.0)


def _network(dims: tuple[int, ...], params: GridCellParams | HeadDirectionParams) -> WrappedAttractor:
    n = len(dims)
    return WrappedAttractor(
        dims,
        excite=Kernel.gaussian((params.excite_size,) * n, (params.excite_sigma,) * n),
        inhibit=Kernel.gaussian((params.inhibit_size,) * n, (params.inhibit_sigma,) * n),
        global_inhibition=params.global_inhibition,
        window=params.window,
    )


class ConjunctivePoseCells:
    """Both networks and the per-frame order of notes §6 (steps 4–7)."""

    def __init__(self, grid: GridCellParams | None = None, head: HeadDirectionParams | None = None) -> None:
        self.grid_params = grid or GridCellParams()
        self.head_params = head or HeadDirectionParams()
        self.grid = _network(self.grid_params.dims, self.grid_params)
        self.head = _network(self.head_params.dims, self.head_params)
        # Starting state (notes §2): the grid packet at the cube's centre, the head packet at cell (0, 0).
        self.grid.set_single(tuple(n // 2 for n in self.grid_params.dims))
        self.head.set_single((0, 0))
        self.codes = _codes(self.grid.decode(), self.head.decode())

    @property
    def yaw_rad(self) -> float:
        """The head-direction packet's yaw, in radians: what drives the grid cells' planar shift."""
        return self.codes.head[0] * 2.0 * math.pi / self.head_params.dims[0]

    def calibrate(self, codes: Codes, decay: float) -> bool:
        """Inject a familiar view's energy at the codes its template stored (Eqs. 10–11, code form); whether any."""
        grid_energy = injection_energy(self.grid_params.inject_energy, decay)
        head_energy = injection_energy(self.head_params.inject_energy, decay)
        if grid_energy > 0.0:
            self.grid.inject(tuple(round(c) for c in codes.grid), grid_energy)
        if head_energy > 0.0:
            self.head.inject(tuple(round(c) for c in codes.head), head_energy)
        return grid_energy > 0.0 or head_energy > 0.0

    def step(self, forward_m: float, dyaw_rad: float, dz_m: float) -> Codes:
        """One frame of self-motion: head direction first, its yaw into the grid cells; the new codes."""
        head_cells = self.head_params.dims[0] / (2.0 * math.pi)
        self.head.step_attractor()
        self.head.shift((dyaw_rad * head_cells, dz_m / self.head_params.cell_size_height))
        head = self.head.decode()
        yaw = float(head[0]) * 2.0 * math.pi / self.head_params.dims[0]
        v = forward_m / self.grid_params.cell_size
        self.grid.step_attractor()
        self.grid.shift((v * math.cos(yaw), v * math.sin(yaw), dz_m / self.grid_params.cell_size_z))
        grid = self.grid.decode()
        self.codes = _codes(grid, head)
        return self.codes

    def snapshot(self) -> dict[str, FloatArray]:
        """Both networks' activity and the codes, as arrays (keys ``ns_*``: the engine snapshot's)."""
        return {"ns_grid_activity": self.grid.activity.copy(), "ns_head_activity": self.head.activity.copy(),
                "ns_codes": self.codes.as_array()}

    @classmethod
    def restore(cls, state: Mapping[str, FloatArray], grid: GridCellParams | None = None,
                head: HeadDirectionParams | None = None) -> ConjunctivePoseCells:
        """The networks as :meth:`snapshot` saved them."""
        cells = cls(grid, head)
        if state["ns_grid_activity"].shape != cells.grid.activity.shape or (
                state["ns_head_activity"].shape != cells.head.activity.shape):
            raise ValueError("the saved networks' sizes differ from these parameters")
        cells.grid.activity = np.array(state["ns_grid_activity"], dtype=np.float64)
        cells.head.activity = np.array(state["ns_head_activity"], dtype=np.float64)
        codes = state["ns_codes"]
        cells.codes = _codes(codes[:3], codes[3:5])
        return cells

    def code_distance(self, a: Codes, b: Codes) -> float:
        """The 5-D wrapped cell distance of the experience decision (notes §7.1, Eq. 22), unit weights."""
        dims = (*self.grid_params.dims, *self.head_params.dims)
        return float(wrapped_distance(a.as_array(), b.as_array(), dims))


def _codes(grid: FloatArray, head: FloatArray) -> Codes:
    return Codes(grid=(float(grid[0]), float(grid[1]), float(grid[2])), head=(float(head[0]), float(head[1])))

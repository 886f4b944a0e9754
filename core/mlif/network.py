"""One PC-MLIF network: a wrapping 3-D lattice of MLIF neurons with CAN dynamics (Pirozzo et al. 2024, Eqs 4–12).

One SLAM update (:meth:`MlifNetwork.attract` then :meth:`MlifNetwork.shift`) runs:

1. currents (Eqs 4–8): ``i = g·(P ⊛ ε − P ⊛ ψ)``, ε and ψ products of per-axis Gaussians (Eq. 4) over the
   wrapped distances of Eq. 6, ψ the wider inhibitory kernel (Eq. 7 — ψ enters with a negative sign);
2. ``NEURON_STEPS`` forward-Euler steps of every neuron under its current (:mod:`core.mlif.neuron`, Eq. 2);
3. the activity matrix from the neurons, then global inhibition (a constant subtracted, floored at 0) and
   normalisation to a total of 1;
4. path integration (Eqs 9–12): the activity and the membrane potentials move together by the commanded cells,
   split between the floor and ceiling shifts of each axis with weights ``1 − frac`` and ``frac``.

Decisions where the paper is silent (it gives none of these):

* **Kernels**: ε from ``pc_w_e_dim``/``pc_w_e_var``, ψ from ``pc_w_i_dim``/``pc_w_i_var`` (the CAN's keys), each
  normalised to a total of 1 as OpenRatSLAM's, so a uniform activity gets no net current.
* **Current scaling**: ``g`` makes the largest current of the update equal the paper's test current,
  ``PEAK_CURRENT`` = 1.5 µA (Fig. 2's step): the packet's peak neuron is driven as the paper's figure neuron
  (steady state ``I·M`` ≈ 28.5 mV > v_th, so it fires about every 21 ms), the flanks below threshold, the
  inhibited surround hyperpolarised. Activity is normalised, so only this ratio is meaningful.
* **Neuron steps per SLAM update**: ``NEURON_STEPS`` = 20 (20 ms at Δt = 1 ms): about one period of the peak
  neuron, so the peak fires about once per update. Membrane potentials and memristor states persist between
  updates (the neurons' memory); the potentials move with the packet in path integration, the memristors stay
  (a device does not move).
* **Activity = potential or rate**: the threshold crossings of the update counted fractionally,
  ``A = spikes + max(V, 0)/v_th`` after the update's steps: below threshold it is the membrane potential (the
  paper's "membrane potentials form the activity matrix", in units of v_th); a neuron that fired does not drop
  below one that did not because of its reset.
* **Global inhibition**: ``GLOBAL_INHIBITION`` = 0.05 (1 mV of potential) subtracted from A, floored at 0.
* Path integration uses floor brackets in Eq. 10 (without them Eq. 12's fractions are 0) and moves the packet
  with the motion (source cell = cell − shift).

torch float64 on the CPU, no random numbers; every operation is elementwise, a roll, an exact maximum or an exact
sum (``math.fsum``): same inputs, same bits, whatever the box or the thread count. No CPU operation used here has
a nondeterministic implementation, so ``torch.use_deterministic_algorithms`` changes nothing and is not set
(it is process-global). A ``mapserver process`` run on one thread and on two gives the same map file, byte for
byte (checked on the ``loop`` log).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

from core.mlif.neuron import DTYPE, MemristorParams, MlifState, NeuronParams, euler_step

NEURON_STEPS = 20
"""Euler steps (Δt = 1 ms) per SLAM update."""
PEAK_CURRENT = 1.5e-6
"""Amperes: the largest current of an update (the paper's Fig. 2 step)."""
GLOBAL_INHIBITION = 0.05
"""Activity units (v_th): subtracted from every neuron's activity before normalisation."""
V_FLUSH = 1e-9
"""Volts: a potential closer than this to 0 after an update is set to 0 (:meth:`MlifNetwork.attract`)."""


@dataclass(frozen=True, slots=True)
class KernelSpec:
    """Excitatory and inhibitory kernel sizes (odd, cells) and Gaussian widths (Eq. 4's var_axis)."""

    excite_size: int
    excite_var: float
    inhibit_size: int
    inhibit_var: float


def axis_taps(dim: int, size: int, var: float) -> list[tuple[int, float]]:
    """Return Eq. 4's Gaussian on one axis as (offset, weight) taps, normalised to total 1, offsets ascending.

    Offsets run over ``−size//2 .. size//2``, each taken mod ``dim`` (Eq. 6) and written in (−dim/2, dim/2], so
    taps that land on the same cell of a short axis add up (an axis of one cell gets one tap of weight 1) and on
    an axis longer than the kernel they are the signed offsets a roll inside a box needs.
    """
    half = size // 2
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    weights = np.exp(-(offsets * offsets) / (2.0 * var * var)) / (var * math.sqrt(2.0 * math.pi))
    weights /= weights.sum()
    merged: dict[int, float] = {}
    for offset, weight in zip(offsets.astype(int).tolist(), weights.tolist(), strict=True):
        key = offset % dim
        key = key - dim if key > dim // 2 else key
        merged[key] = merged.get(key, 0.0) + weight
    return sorted(merged.items())


def spread(cells: torch.Tensor, taps: list[list[tuple[int, float]]]) -> torch.Tensor:
    """Return the wrapped convolution of ``cells`` with a separable kernel, one axis after the other (Eqs 5, 7)."""
    out = cells
    for axis, axis_taps_ in enumerate(taps):
        acc = torch.zeros_like(out)
        for offset, weight in axis_taps_:
            acc = acc + weight * torch.roll(out, shifts=offset, dims=axis)
        out = acc
    return out


def shift_axis(cells: torch.Tensor, cells_moved: float, axis: int) -> torch.Tensor:
    """Return ``cells`` moved ``cells_moved`` along ``axis`` with wrap (Eqs 9–12 on one axis).

    ``⌊s⌋`` takes weight ``1 − frac`` and ``⌊s⌋ + 1`` weight ``frac`` (Eq. 11's f); a whole move is one roll.
    """
    if cells_moved == 0.0:
        return cells
    whole = math.floor(cells_moved)
    frac = cells_moved - whole
    moved = torch.roll(cells, shifts=whole, dims=axis)
    if frac == 0.0:
        return moved
    return (1.0 - frac) * moved + frac * torch.roll(cells, shifts=whole + 1, dims=axis)


class MlifNetwork:
    """Activity, neurons and memristors of one 3-D PC-MLIF lattice, axes (x, y, third); see the module docstring.

    Args:
        shape: cells per axis (x, y, z) or (x, y, θ).
        kernels: the excitation and inhibition kernels.
        neuron: MLIF membrane parameters (the paper's).
        memristor: HP memristor parameters (chosen; :mod:`core.mlif.neuron`).
    """

    def __init__(
        self, shape: tuple[int, int, int], kernels: KernelSpec, neuron: NeuronParams | None = None,
        memristor: MemristorParams | None = None,
    ) -> None:
        self.shape = shape
        self.neuron = neuron or NeuronParams()
        self.memristor = memristor or MemristorParams()
        self.excite = [axis_taps(d, kernels.excite_size, kernels.excite_var) for d in shape]
        self.inhibit = [axis_taps(d, kernels.inhibit_size, kernels.inhibit_var) for d in shape]
        self.reach = max(kernels.excite_size, kernels.inhibit_size) // 2
        """Cells a kernel reaches from its centre."""
        self.activity = torch.zeros(shape, dtype=DTYPE)
        self.activity[tuple(d // 2 for d in shape)] = 1.0
        self.state = MlifState.resting(shape, self.neuron, self.memristor)
        self.spikes = 0
        """Spikes of the last update (all neurons)."""

    def currents(self, activity: torch.Tensor) -> torch.Tensor:
        """Return each neuron's input current (Eq. 8), amperes, the largest scaled to ``PEAK_CURRENT``.

        ``activity`` is the lattice or a box of it whose faces hold no activity within a kernel's reach (then a
        roll inside the box brings in only zeros, and the box's currents are the lattice's).
        """
        net = spread(activity, self.excite) - spread(activity, self.inhibit)
        peak = float(net.max())
        if not peak > 0.0:
            return torch.zeros_like(net)
        return net * (PEAK_CURRENT / peak)

    def attract(self) -> None:
        """Run the attractor step: currents, ``NEURON_STEPS`` Euler steps, activity, global inhibition, normalise.

        Only the box of :meth:`box` is computed: outside it activity, potential and current are 0, so a neuron
        there stays at 0 V, its memristor does not drift (no current) and its activity is 0 — as the whole
        lattice would give. Potentials within ``V_FLUSH`` of 0 are set to 0 after the update (their activity is
        ~1e-7 of v_th, far under the global inhibition; without it every cell the packet ever crossed would stay
        in the box, its potential decaying through subnormal numbers). Should every neuron end inhibited, the
        activity restarts as one cell at its peak before the step, so the network never holds nothing.
        """
        index = np.ix_(*self.box())
        v_all, x_all = self.state.v.numpy(), self.state.x.numpy()
        state = MlifState(torch.from_numpy(v_all[index]), torch.from_numpy(x_all[index]))
        current = self.currents(torch.from_numpy(self.activity.numpy()[index]))
        fired = torch.zeros_like(current)
        for _ in range(NEURON_STEPS):
            fired = fired + euler_step(state, current, self.neuron, self.memristor).to(DTYPE)
        state.v = torch.where(state.v.abs() < V_FLUSH, torch.zeros_like(state.v), state.v)
        self.spikes = int(fired.sum())
        activity = fired + state.v.clamp(min=0.0) / self.neuron.v_th
        activity = (activity - GLOBAL_INHIBITION).clamp(min=0.0)
        v_all, x_all = v_all.copy(), x_all.copy()
        v_all[index], x_all[index] = state.v.numpy(), state.x.numpy()
        self.state = MlifState(torch.from_numpy(v_all), torch.from_numpy(x_all))
        values = activity.numpy()
        total = math.fsum(values[values > 0.0].tolist())  # exact: the same whatever the box, order or threads
        if not total > 0.0:
            restart = torch.zeros_like(self.activity)
            restart.view(-1)[int(torch.argmax(self.activity))] = 1.0
            self.activity = restart
            return
        cells = np.zeros(self.shape, dtype=np.float64)
        cells[index] = (activity / total).numpy()
        self.activity = torch.from_numpy(cells)

    def box(self) -> list[np.ndarray]:
        """Return per axis the cells an update must compute.

        That is the shortest wrapped run over every cell with activity or potential, widened by the kernels'
        reach on both sides (the whole axis when that covers it).
        """
        support = (self.activity.numpy() != 0.0) | (self.state.v.numpy() != 0.0)
        reach = self.reach
        runs = []
        for axis, d in enumerate(self.shape):
            occupied = np.flatnonzero(support.any(axis=tuple(a for a in range(3) if a != axis)))
            if occupied.size == 0:
                occupied = np.asarray([d // 2])
            gaps = np.diff(np.append(occupied, occupied[0] + d))
            widest = int(np.argmax(gaps))
            start = int(occupied[(widest + 1) % occupied.size])
            length = d - int(gaps[widest]) + 1
            if length + 2 * reach >= d:
                runs.append(np.arange(d))
            else:
                runs.append((start - reach + np.arange(length + 2 * reach)) % d)
        return runs

    def shift(self, moves: torch.Tensor | tuple[float, float, float]) -> None:
        """Move activity and potentials by ``moves`` cells (x, y, third) — Eqs 9–12 with one move for all cells."""
        dx, dy, dthird = (float(m) for m in moves)
        for name in ("activity", "v"):
            cells = self.activity if name == "activity" else self.state.v
            for axis, amount in ((0, dx), (1, dy), (2, dthird)):
                cells = shift_axis(cells, amount, axis)
            if name == "activity":
                self.activity = cells
            else:
                self.state.v = cells

    def shift_layers(self, forward_cells: float, cos: list[float], sin: list[float], dthird: float) -> None:
        """Move each third-axis layer k by ``forward_cells·(cos_k, sin_k)`` in (x, y), then all by ``dthird``.

        This is Eqs 9–12 for the heading network: layer k holds heading θ_k and moves along it. Layers without
        activity or potential are left as they are (a moved zero is zero).
        """
        support = (self.activity != 0.0) | (self.state.v != 0.0)
        occupied = torch.nonzero(support.any(dim=1).any(dim=0)).flatten().tolist()
        for name in ("activity", "v"):
            cells = self.activity if name == "activity" else self.state.v
            if forward_cells != 0.0:
                cells = cells.clone()
                for k in occupied:
                    layer = shift_axis(cells[:, :, k], forward_cells * cos[k], 0)
                    cells[:, :, k] = shift_axis(layer, forward_cells * sin[k], 1)
            cells = shift_axis(cells, dthird, 2)
            if name == "activity":
                self.activity = cells
            else:
                self.state.v = cells

    def inject(self, cell: tuple[int, int, int], energy: float) -> None:
        """Add ``energy`` to one cell's activity (local-view calibration; [A] Eq. 4 with β at the cell)."""
        index = tuple(int(c) % d for c, d in zip(cell, self.shape, strict=True))
        self.activity[index] += energy

    def decode(self, radius: int) -> np.ndarray:
        """Return the packet centre (cells, each in [0, n)): circular means of the ±``radius`` window's marginals.

        The window is centred on the first maximum (C order) and narrowed on axes shorter than 2·radius + 1.
        """
        cells = self.activity.numpy()
        peak = np.unravel_index(int(np.argmax(cells)), self.shape)
        windows = []
        for c, d in zip(peak, self.shape, strict=True):
            r = min(radius, (d - 1) // 2)
            windows.append((int(c) + np.arange(-r, r + 1)) % d)
        box = cells[np.ix_(*windows)]
        centre = np.empty(3, dtype=np.float64)
        for axis in range(3):
            marginal = box.sum(axis=tuple(a for a in range(3) if a != axis))
            d = self.shape[axis]
            angles = windows[axis] * (2.0 * math.pi / d)
            value = math.atan2(float(np.dot(marginal, np.sin(angles))), float(np.dot(marginal, np.cos(angles))))
            centre[axis] = (value * d / (2.0 * math.pi)) % d
        return centre

    def snapshot(self, prefix: str) -> dict[str, np.ndarray]:
        """Return activity, potentials and memristor states as float64 arrays under ``prefix``."""
        return {f"{prefix}_activity": self.activity.numpy().copy(), f"{prefix}_v": self.state.v.numpy().copy(),
                f"{prefix}_x": self.state.x.numpy().copy()}

    def load(self, state: Mapping[str, np.ndarray], prefix: str) -> None:
        """Set activity, potentials and memristor states from :meth:`snapshot` arrays (exactly)."""
        for key in ("activity", "v", "x"):
            array = np.asarray(state[f"{prefix}_{key}"], dtype=np.float64)
            if array.shape != self.shape:
                msg = f"MLIF {prefix} {key} shape {array.shape} does not match the lattice {self.shape}"
                raise ValueError(msg)
            tensor = torch.from_numpy(array.copy())
            if key == "activity":
                self.activity = tensor
            elif key == "v":
                self.state.v = tensor
            else:
                self.state.x = tensor

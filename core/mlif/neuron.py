"""MLIF neurons: a leaky integrate-and-fire membrane whose leak is an HP memristor (Pirozzo et al. 2024, Eqs 1–2).

The circuit (their Fig. 1) is a capacitor C (the membrane) in parallel with a memristor M (the ion channel),
driven by a current ``I_ext``; a switch resets the membrane to ``v_reset`` when it reaches ``v_th``:

* Eq. 1: ``dV/dt = (−V + I_ext·M)/τ`` with ``τ = M·C``;
* Eq. 2 (forward Euler, the paper's integration): ``V(t+Δt) = V(t) + Δt/τ·(−V(t) + I_ext·M(t))``; then
  ``V ≥ v_th`` → spike, ``V ← v_reset``.

The paper gives C = 9e−7 F, v_th = 20 mV, v_reset = 0 V and Δt = 1e−3 s (:class:`NeuronParams`).

The memristor is the HP Labs device (Strukov et al., Nature 453, 2008), linear ion drift with Joglekar's window
(Joglekar & Wolf 2009, p = 1), state ``x = w/D ∈ [0, 1]``:

* ``M(x) = R_on·x + R_off·(1 − x)``;
* ``dx/dt = μ_v·R_on/D² · i_M · (1 − (2x − 1)²)``, integrated with the same Euler step; ``i_M = V/M`` is the
  leak current through the device.

The paper names the model but gives none of its parameters; the ones chosen here (:class:`MemristorParams`) are
Strukov's except ``R_off``: R_on = 100 Ω, D = 10 nm, μ_v = 1e−14 m²·s⁻¹·V⁻¹ (Strukov et al.), R_off = 20 kΩ, and
the device is wired so that the leak current of a depolarised membrane drives it towards ``R_off``
(``polarity = −1``), from ``x₀ = 0.05`` (M₀ = 19 005 Ω). Why: the neuron can fire only when
``I_ext·M > v_th`` (M > 13.3 kΩ at the paper's 1.5 µA), and Fig. 3's 18 ms-on / 10 ms-off train at 1.5 µA has
to reach the threshold; with Strukov's R_off = 16 kΩ its response settles at 19.98 mV and never fires, so the
device must sit above 16 kΩ. The drift is slow at these currents (|dx/dt| ≈ 0.01 s⁻¹ at 1 µA): over a figure's
0.6 s the memristance changes by < 1 %, over a 1 000-frame map (20 s of neuron time) by up to ~10 %.

Everything is torch float64 on the CPU, elementwise: the same inputs give the same bits.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

DTYPE = torch.float64


@dataclass(frozen=True, slots=True)
class NeuronParams:
    """The MLIF membrane of Pirozzo et al. (§II, Fig. 1): C, v_th, v_reset and the Euler step Δt."""

    capacitance: float = 9e-7
    """C, farads."""
    v_th: float = 0.02
    """Firing threshold, volts (20 mV)."""
    v_reset: float = 0.0
    """Potential after a spike, volts."""
    dt: float = 1e-3
    """Forward-Euler step Δt of Eq. 2, seconds."""


@dataclass(frozen=True, slots=True)
class MemristorParams:
    """The HP memristor (Strukov et al. 2008) with Joglekar's window; values chosen here (module docstring)."""

    r_on: float = 100.0
    """Ω, fully doped (x = 1)."""
    r_off: float = 20e3
    """Ω, undoped (x = 0)."""
    thickness: float = 10e-9
    """D, metres."""
    mobility: float = 1e-14
    """μ_v, m²·s⁻¹·V⁻¹."""
    polarity: float = -1.0
    """−1: a positive leak current (depolarised membrane) moves x towards 0, M towards R_off."""
    x0: float = 0.05
    """Initial state w/D."""


def memristance(x: torch.Tensor, mem: MemristorParams) -> torch.Tensor:
    """Return ``M(x) = R_on·x + R_off·(1 − x)`` (Strukov et al. Eq. 1), ohms."""
    return mem.r_on * x + mem.r_off * (1.0 - x)


def drift_rate(current: torch.Tensor, x: torch.Tensor, mem: MemristorParams) -> torch.Tensor:
    """Return dx/dt of the linear-drift HP model with Joglekar's window (p = 1) for the device current."""
    window = 1.0 - (2.0 * x - 1.0) ** 2
    return mem.polarity * mem.mobility * mem.r_on / (mem.thickness * mem.thickness) * current * window


@dataclass(slots=True)
class MlifState:
    """Membrane potentials ``v`` (volts) and memristor states ``x`` of a population, same shape."""

    v: torch.Tensor
    x: torch.Tensor

    @classmethod
    def resting(cls, shape: tuple[int, ...], neuron: NeuronParams, mem: MemristorParams) -> MlifState:
        """Return a population at ``v_reset`` with every memristor at ``x₀``."""
        return cls(torch.full(shape, neuron.v_reset, dtype=DTYPE), torch.full(shape, mem.x0, dtype=DTYPE))


def euler_step(
    state: MlifState, current: torch.Tensor, neuron: NeuronParams, mem: MemristorParams
) -> torch.Tensor:
    """Advance ``state`` by one Δt under ``current`` (amperes; Eq. 2) and return where it spiked (bool).

    The membrane and the memristor both step from the values at t (explicit Euler); a neuron at or above
    ``v_th`` after the step spikes and is reset to ``v_reset``.
    """
    m = memristance(state.x, mem)
    tau = m * neuron.capacitance
    v = state.v + neuron.dt / tau * (-state.v + current * m)
    x = state.x + neuron.dt * drift_rate(state.v / m, state.x, mem)
    state.x = x.clamp(0.0, 1.0)
    spiked = v >= neuron.v_th
    state.v = torch.where(spiked, torch.full_like(v, neuron.v_reset), v)
    return spiked


def simulate(
    currents: torch.Tensor, neuron: NeuronParams | None = None, mem: MemristorParams | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Run one neuron from rest through ``currents`` (one value per Δt) and return (V, spiked, M) per step.

    V is the potential after each step (after any reset), ``spiked`` where it reached ``v_th``, M the memristance
    after the step. This is the paper's single-neuron test bench (Figs 2–3).
    """
    neuron = neuron or NeuronParams()
    mem = mem or MemristorParams()
    state = MlifState.resting((), neuron, mem)
    steps = int(currents.shape[0])
    v = torch.empty(steps, dtype=DTYPE)
    spikes = torch.zeros(steps, dtype=torch.bool)
    m = torch.empty(steps, dtype=DTYPE)
    for k in range(steps):
        spikes[k] = euler_step(state, currents[k], neuron, mem)
        v[k] = state.v
        m[k] = memristance(state.x, mem)
    return v, spikes, m


def step_current(steps: int, amplitude: float = 1.5e-6) -> torch.Tensor:
    """Return Fig. 2's stimulus: a step of ``amplitude`` amperes (1.5 µA) held for ``steps`` Δt."""
    return torch.full((steps,), amplitude, dtype=DTYPE)


def fig3_current(
    low_amplitude: float = 1.0e-6, high_amplitude: float = 1.5e-6, dt_ms: int = 1
) -> torch.Tensor:
    """Return Fig. 3's stimulus, one value per Δt over 600 ms.

    0–200 ms: pulses of ``low_amplitude``, 10 ms on / 10 ms off; 200–300 ms: none; 300–600 ms: pulses of
    ``high_amplitude`` (the figure's maximum, 1.5 µA), 18 ms on / 10 ms off. The paper gives the timings and
    the maximum; the first train's amplitude is not given (its figure is not in the text we have): 1.0 µA is
    chosen, two thirds of the maximum. (At any amplitude up to 1.5 µA the 10/10 train stays below v_th.)
    """
    t = torch.arange(0, 600, dt_ms, dtype=DTYPE)
    first = (t < 200) & (torch.remainder(t, 20) < 10)
    second = (t >= 300) & (torch.remainder(t - 300, 28) < 18)
    return torch.where(first, low_amplitude, 0.0) + torch.where(second, high_amplitude, 0.0)

"""MLIF neuron tests: Pirozzo et al. 2024 Figs 2–3 with the paper's numbers (C = 9e−7 F, v_th = 20 mV, Δt = 1 ms).

The figures' curves are not in the text we have, only their captions and §II's description: a 1.5 µA step
fires periodically (Fig. 2); a 10 ms-on / 10 ms-off train over 0–200 ms never reaches v_th, a pause follows
(200–300 ms), and an 18 ms-on / 10 ms-off train of the maximum amplitude (1.5 µA) over 300–600 ms reaches it
and resets (Fig. 3). The expected spike times are computed here independently: the Euler recursion of Eq. 2 in
plain Python floats with the memristance frozen at its initial value (the memristor moves < 0.1 % in 0.6 s).
"""

from __future__ import annotations

import math

import torch

from core.mlif.neuron import (
    MemristorParams,
    MlifState,
    NeuronParams,
    euler_step,
    fig3_current,
    memristance,
    simulate,
    step_current,
)

NEURON = NeuronParams()
MEM = MemristorParams()
M0 = MEM.r_on * MEM.x0 + MEM.r_off * (1 - MEM.x0)  # 19 005 Ω


def frozen_euler_spikes(currents: list[float], m: float = M0) -> list[int]:
    """Steps at which Eq. 2 with a fixed memristance ``m`` reaches v_th (plain floats, reset to 0)."""
    v, spikes = 0.0, []
    tau = m * 9e-7
    for k, i in enumerate(currents):
        v = v + 1e-3 / tau * (-v + i * m)
        if v >= 0.02:
            spikes.append(k)
            v = 0.0
    return spikes


def test_the_papers_constants() -> None:
    assert (NEURON.capacitance, NEURON.v_th, NEURON.v_reset, NEURON.dt) == (9e-7, 0.02, 0.0, 1e-3)
    assert M0 == 19005.0


def test_one_euler_step_is_eq_2() -> None:
    state = MlifState(torch.tensor(0.01, dtype=torch.float64), torch.tensor(0.05, dtype=torch.float64))
    euler_step(state, torch.tensor(1.5e-6, dtype=torch.float64), NEURON, MEM)
    tau = M0 * 9e-7
    assert float(state.v) == 0.01 + 1e-3 / tau * (-0.01 + 1.5e-6 * M0)


def test_fig2_a_step_of_1_5_microamps_fires_every_21_ms() -> None:
    v, spikes, _ = simulate(step_current(200))
    fired = torch.nonzero(spikes).flatten().tolist()
    # closed form of the Euler recursion V_n = I·M·(1 − (1 − Δt/τ)^n): first n with V_n ≥ v_th
    n = math.ceil(math.log(1 - 0.02 / (1.5e-6 * M0)) / math.log(1 - 1e-3 / (M0 * 9e-7)))
    assert n == 21
    assert fired == [n - 1 + 21 * k for k in range(9)] == frozen_euler_spikes([1.5e-6] * 200)
    assert float(v.max()) < 0.02  # reset at v_th, never above
    assert all(float(v[k]) == 0.0 for k in fired)  # reset to 0 V
    assert float(v[fired[0] - 1]) > 0.019  # it rose to just under the threshold before firing


def test_a_step_under_v_th_over_m_never_fires_and_settles_at_i_times_m() -> None:
    current = 0.9 * 0.02 / M0  # steady state I·M = 18 mV < v_th
    v, spikes, m = simulate(step_current(1000, current))
    assert not bool(spikes.any())
    # it settles at I·M(t); M drifted up by ~0.2 % in the second (towards R_off: the membrane is depolarised)
    assert abs(float(v[-1]) - current * float(m[-1])) < 1e-4 * 0.02  # lagging the drift by ~τ
    assert 0.0 < float(m[-1]) / M0 - 1.0 < 3e-3


def test_fig3_the_10_10_train_never_fires_and_the_18_10_train_does() -> None:
    currents = fig3_current()
    v, spikes, m = simulate(currents)
    fired = torch.nonzero(spikes).flatten().tolist()
    assert fired == frozen_euler_spikes(currents.tolist()) == [340, 373, 424, 457, 508, 541, 592]
    assert not bool(spikes[:300].any())  # 0–200 ms: rises and decays below v_th; 200–300 ms: no stimulus
    assert float(v[199]) < float(v[:200].max()) < 0.02
    assert float(v[299]) < 1e-4  # it leaked away in the pause
    # even at the maximum amplitude a 10/10 train would not fire (its potential settles at ~18 mV)
    assert not bool(simulate(fig3_current(low_amplitude=1.5e-6))[1][:300].any())
    assert abs(float(m[-1]) - M0) / M0 < 1e-3


def test_hp_memristor_bounds_and_drift_direction() -> None:
    x = torch.tensor([0.0, 1.0], dtype=torch.float64)
    assert memristance(x, MEM).tolist() == [MEM.r_off, MEM.r_on]
    # a depolarised membrane drives the device towards R_off (it becomes more excitable) …
    _, _, m = simulate(step_current(300, 1.0e-6))
    assert float(m[-1]) > float(m[1]) > float(m[0]) == M0  # step 0 starts from 0 V: no current yet
    # … and with no current it keeps its state (the memristor "remembers")
    _, _, m = simulate(torch.zeros(300, dtype=torch.float64))
    assert bool((m == M0).all())

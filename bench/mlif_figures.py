"""Draw the MLIF neuron's responses of Pirozzo et al. (2024) Figs 2–3 as PNGs (``core.mlif.neuron.simulate``).

Usage: python bench/mlif_figures.py [--out docs/figures]

Writes ``mlif-fig2-step.png`` (a 1.5 µA step, 200 ms) and ``mlif-fig3-pulses.png`` (Fig. 3's pulse trains, 600 ms):
membrane potential in mV with the 20 mV threshold, and the input current in µA. The last line of stdout is one
JSON object: {"files": [...], "fig2_spike_ms": [...], "fig3_spike_ms": [...]} (spike times, ms after the start,
the step's end).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from core.mlif.neuron import NeuronParams, fig3_current, simulate, step_current
from mapserver.plotting import new_figure, png_bytes


def draw(currents: torch.Tensor, title: str, path: Path) -> list[int]:
    """Simulate the neuron through ``currents``, draw potential and current against time, return spike times (ms)."""
    v, spikes, _ = simulate(currents)
    t = torch.arange(1, currents.shape[0] + 1, dtype=torch.float64)  # step k ends at (k + 1) ms
    fig = new_figure((8.0, 4.5))
    top, bottom = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    top.plot(t.numpy(), v.numpy() * 1e3, color="tab:blue", linewidth=1.0, label="membrane potential V")
    top.axhline(NeuronParams().v_th * 1e3, color="tab:red", linestyle="--", linewidth=0.8, label="v_th = 20 mV")
    top.set_ylabel("V (mV)")
    top.set_title(title)
    top.legend(loc="upper right", fontsize=8)
    bottom.step(t.numpy(), currents.numpy() * 1e6, where="post", color="tab:gray", linewidth=1.0)
    bottom.set_ylabel("I_ext (µA)")
    bottom.set_xlabel("time (ms)")
    fig.tight_layout()
    path.write_bytes(png_bytes(fig))
    return [int(k) + 1 for k in torch.nonzero(spikes).flatten().tolist()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/figures")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    fig2, fig3 = out / "mlif-fig2-step.png", out / "mlif-fig3-pulses.png"
    spikes2 = draw(step_current(200), "MLIF neuron, 1.5 µA step (Pirozzo et al. Fig. 2)", fig2)
    spikes3 = draw(fig3_current(), "MLIF neuron, pulse trains 10/10 ms at 1.0 µA, 18/10 ms at 1.5 µA (Fig. 3)", fig3)
    print(json.dumps({"files": [str(fig2), str(fig3)], "fig2_spike_ms": spikes2, "fig3_spike_ms": spikes3}))


if __name__ == "__main__":
    main()

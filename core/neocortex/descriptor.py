"""The TM-winner sequence descriptor D_t and its overlap matching (PoseidonSLAM Eqs 4.4–4.10).

Descriptor (choices for the thesis's open points, notes §11.7):

* the winner cells of the last ``window`` steps are kept (``sv_tm_window`` = 7);
* **interval union** (Eq. 4.5): the current run grows by one while the winners overlap those of the
  previous step by at least ``theta_alpha`` (|W_t ∩ W_{t−1}| / |W_t|), else restarts at 1; the union
  covers the last K_t = min(window, max(theta_rho, run)) steps, so at least ``theta_rho`` steps and the
  whole window along a stable run (``interval_mode`` off: always the whole window);
* **top-k cap**: the ``topk`` cells that occur most often in those K_t steps; ties go to the cell seen
  most recently, then to the lower cell id. D_t is returned sorted.

Matching against the prototypes {D_ℓ}: I = |D_t ∩ D_ℓ| (4.6), R = I/|D_t| (4.7), ℓ* = argmax R (4.8),
ties broken by the larger IoU = I/|D_t ∪ D_ℓ| when ``iou_tiebreak`` (then the lower id); accepted when
I ≥ I_min and R ≥ τ_R (4.9) and, with the F1 gate, Dice F1 = 2I/(|D_t| + |D_ℓ|) ≥ τ_F1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.arrays import IntArray


@dataclass(frozen=True)
class MatchGates:
    """The acceptance gates of Eq. 4.9."""

    min_intersection: int = 12
    tau_r: float = 0.30
    f1_gate: bool = True
    min_f1: float = 0.55
    iou_tiebreak: bool = True


@dataclass(frozen=True)
class Match:
    """The best prototype ℓ* with its scores; ``accepted`` says whether Eq. 4.9 holds."""

    index: int
    intersection: int
    recall: float
    f1: float
    iou: float
    accepted: bool


def interval_length(run: int, window: int, theta_rho: int, interval_mode: bool) -> int:
    """Return K_t, the number of recent steps the union covers."""
    if not interval_mode:
        return window
    return min(window, max(theta_rho, run))


def cap_topk(history: list[IntArray], topk: int) -> IntArray:
    """Return the sorted ``topk`` most frequent cells of ``history`` (oldest first); ties: most recent, lower id."""
    if not history:
        return np.empty(0, dtype=np.int64)
    cells = np.concatenate(history).astype(np.int64)
    if cells.size == 0:
        return cells
    when = np.concatenate([np.full(h.size, i, dtype=np.int64) for i, h in enumerate(history)])
    ids, inverse, counts = np.unique(cells, return_inverse=True, return_counts=True)
    last = np.full(ids.size, -1, dtype=np.int64)
    np.maximum.at(last, inverse, when)
    order = np.lexsort((ids, -last, -counts))  # last key first: count desc, recency desc, id asc
    return np.sort(ids[order[:topk]])


def overlap_scores(descriptor: IntArray, prototypes: IntArray, sizes: IntArray) -> tuple[np.ndarray, ...]:
    """Return (I, R, F1, IoU) of ``descriptor`` against every prototype row (−1 padded, ``sizes`` entries each)."""
    n = descriptor.size
    inter = np.isin(prototypes, descriptor).sum(axis=1).astype(np.int64) if n else np.zeros(len(prototypes), np.int64)
    sizes = sizes.astype(np.float64)
    recall = inter / n if n else np.zeros(inter.shape)
    total = n + sizes
    f1 = np.divide(2.0 * inter, total, out=np.zeros(inter.shape), where=total > 0)
    union = total - inter
    iou = np.divide(inter, union, out=np.zeros(inter.shape), where=union > 0)
    return inter, recall, f1, iou


def best_match(descriptor: IntArray, prototypes: IntArray, sizes: IntArray, gates: MatchGates) -> Match | None:
    """Return ℓ* (Eq. 4.8) with its scores and the Eq. 4.9 verdict, or None without prototypes."""
    if len(prototypes) == 0:
        return None
    inter, recall, f1, iou = overlap_scores(descriptor, prototypes, sizes)
    second = iou if gates.iou_tiebreak else np.zeros_like(iou)
    order = np.lexsort((np.arange(recall.size), -second, -recall))
    best = int(order[0])
    accepted = bool(inter[best] >= gates.min_intersection and recall[best] >= gates.tau_r)
    if gates.f1_gate:
        accepted = accepted and bool(f1[best] >= gates.min_f1)
    return Match(best, int(inter[best]), float(recall[best]), float(f1[best]), float(iou[best]), accepted)

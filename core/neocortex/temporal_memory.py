"""HTM Temporal Memory on torch tensors (thesis Table 3.3 routines, Table 4.1/5.1 values), vectorised.

Cells: ``columns × cells_per_column``, cell id = column·cells + i. Distal segments live in one pool:
``seg_cell`` (G,), ``syn_pre`` (G, M) presynaptic cell or −1, ``syn_perm`` (G, M) float32.

One step with the active columns C (from the spatial pooler) and the previous active cells a′:

* a segment is **active** when ≥ ``activation_threshold`` of its synapses are connected
  (perm ≥ ``connected``) to a′, **matching** when ≥ ``min_threshold`` of its synapses (any
  permanence) go to a′; a cell is **predicted** when it has an active segment;
* a column of C with predicted cells activates those cells (they are its winners); a column without
  **bursts**: all its cells become active, and its winner is the cell of its best matching segment
  (most active potential synapses, ties: oldest segment) or, without one, the least-used cell (fewest
  segments; ties broken by a fixed hash of (step, column), the deterministic stand-in for a random pick);
* learning: the learning segments (active segments of predicted columns, best matching segments of
  bursting columns) get +inc on synapses to a′ and −dec on the others (clipped to [0, 1]; a synapse at
  0 is removed), then grow ``max_new − numActivePotential`` synapses to previous winner cells they lack,
  at ``initial`` permanence (free slots first, then the weakest); a bursting column without a matching
  segment gets a new segment on its winner with ``max_new`` synapses to previous winners; matching
  segments in inactive columns lose ``predicted_decrement`` on synapses to a′.

Counts are exact integers and updates elementwise, so the result does not depend on the thread count.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import cast

import numpy as np
import torch

from core.arrays import IntArray

HASH_A = 2654435761  # Knuth's multiplicative hash constant
HASH_B = 40503
INDEX_REBUILD_MIN = 4096  # the synapse index is rebuilt after this many slots written (or a quarter of its own)


@dataclass(frozen=True)
class TMConfig:
    """Temporal Memory parameters (names as NuPIC's, values from the thesis's tables)."""

    columns: int
    cells_per_column: int = 40
    activation_threshold: int = 5
    min_threshold: int = 3
    initial_permanence: float = 0.55
    connected_permanence: float = 0.5
    max_new_synapse_count: int = 20
    max_synapses_per_segment: int = 32
    permanence_increment: float = 0.008
    permanence_decrement: float = 0.012
    predicted_segment_decrement: float = 0.0


class SynapseIndex:
    """Where each presynaptic cell's synapses sit: flat slots ``segment·M + slot``, grouped by cell (CSR).

    Built from the segment pool, then told of every slot written since (:meth:`wrote`); slots emptied or
    overwritten since are not removed but fail :meth:`active_slots`'s check that the slot still holds the cell.
    Rebuilt when the slots written since reach a quarter of those indexed. A step then looks up the synapses of
    the previous active cells only (their fan-out) instead of every slot of every segment.
    """

    def __init__(self, cells: int, device: torch.device) -> None:
        self.cells, self.device = cells, device
        self.slots = torch.empty(0, dtype=torch.int64, device=device)
        self.starts = torch.zeros(cells + 1, dtype=torch.int64, device=device)
        self._recent = torch.empty(4096, dtype=torch.int64, device=device)  # slots written since: [:recent_count]
        self.recent_count = 0
        self.stale = True

    def rebuild(self, pre: torch.Tensor) -> None:
        """Index the presynaptic cells ``pre`` (the pool's used part flattened, −1 empty)."""
        slots = torch.nonzero(pre >= 0).flatten()
        cells = pre[slots]
        self.slots = slots[torch.argsort(cells, stable=True)]
        counts = torch.bincount(cells, minlength=self.cells)
        self.starts = torch.cat([torch.zeros(1, dtype=torch.int64, device=self.device), torch.cumsum(counts, 0)])
        self.recent_count, self.stale = 0, False

    def wrote(self, slots: torch.Tensor) -> None:
        """Note flat slots given a new presynaptic cell since the last rebuild."""
        end = self.recent_count + int(slots.numel())
        if end > self._recent.numel():
            grown = torch.empty(max(end, 2 * self._recent.numel()), dtype=torch.int64, device=self.device)
            grown[: self.recent_count] = self._recent[: self.recent_count]
            self._recent = grown
        self._recent[self.recent_count : end] = slots.reshape(-1)
        self.recent_count = end

    def due(self) -> bool:
        """Return whether a rebuild is due (built never, or a quarter of the indexed slots written since)."""
        return self.stale or self.recent_count > max(INDEX_REBUILD_MIN, self.slots.numel() // 4)

    def active_slots(self, pre: torch.Tensor, active_ids: torch.Tensor, padded: torch.Tensor) -> torch.Tensor:
        """Return the sorted flat slots of ``pre`` whose presynaptic cell is active.

        ``active_ids``: a′'s cells; ``padded``: a′ as a mask with a False appended, so an empty slot reads False.
        """
        first = self.starts[active_ids]
        lengths = self.starts[active_ids + 1] - first
        total = int(lengths.sum())
        found = torch.empty(0, dtype=torch.int64, device=self.device)
        if total:
            shift = torch.repeat_interleave(first - (torch.cumsum(lengths, 0) - lengths), lengths)
            slots = self.slots[shift + torch.arange(total, device=self.device)]
            found = slots[pre[slots] == torch.repeat_interleave(active_ids, lengths)]  # still that cell's
        if self.recent_count:
            recent = self._recent[: self.recent_count]
            found = torch.cat([found, recent[torch.take(padded, pre[recent])]])
        return cast(torch.Tensor, torch.unique(found))  # a slot rewritten since may be listed twice


class TemporalMemory:
    """Sequence memory over the spatial pooler's columns; its whole state is a few tensors."""

    def __init__(self, config: TMConfig, device: torch.device | str = "cpu") -> None:
        self.cfg = config
        self.device = torch.device(device)
        self.cells = config.columns * config.cells_per_column
        m = config.max_synapses_per_segment
        self.seg_cell = torch.empty(0, dtype=torch.int64, device=self.device)
        self.syn_pre = torch.empty((0, m), dtype=torch.int64, device=self.device)
        self.syn_perm = torch.empty((0, m), dtype=torch.float32, device=self.device)
        self.segments = 0
        self.prev_active = torch.zeros(self.cells, dtype=torch.bool, device=self.device)
        self.prev_winners = torch.empty(0, dtype=torch.int64, device=self.device)
        self.step_count = 0
        self._no_cell = torch.zeros(1, dtype=torch.bool, device=self.device)
        self.index = SynapseIndex(self.cells, self.device)
        self._active_ids = (self.prev_active, torch.empty(0, dtype=torch.int64, device=self.device))
        self._cell_segments = torch.zeros(self.cells, dtype=torch.int64, device=self.device)  # segments per cell

    # ------------------------------------------------------------------ step
    def synapse_activity(self) -> torch.Tensor:
        """Return the (G, M) bool mask of synapses whose presynaptic cell is in a′ (every slot of every segment)."""
        return torch.take(self._padded_active(), self.syn_pre[: self.segments])

    def _padded_active(self) -> torch.Tensor:
        """Return a′ as a mask with a False appended: an empty synapse slot (−1) reads that False."""
        return torch.cat([self.prev_active, self._no_cell])

    def compute(self, active_columns: torch.Tensor, learn: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """Advance one step; return (active cells, winner cells), both sorted int64 cell ids.

        Only the segments with a synapse to a′ can be active, matching or learn (the thresholds are ≥ 1), so the
        step works on those (``seg``, ascending ids), found through the synapse index, and on cell ids, not on
        masks over every segment and cell.
        """
        cfg = self.cfg
        cpc = cfg.cells_per_column
        padded = self._padded_active()
        seg, n_pot, connected = self._indexed_activity(padded)
        seg_active = connected >= cfg.activation_threshold
        seg_match = n_pot >= cfg.min_threshold
        seg_cell = self.seg_cell[seg]
        seg_col = seg_cell // cpc
        col_on = torch.zeros(cfg.columns, dtype=torch.bool, device=self.device)
        col_on[active_columns.to(self.device)] = True
        predicted_ids = seg_cell[seg_active]  # cells with an active segment (repeated per segment)
        predicted_cols = torch.zeros(cfg.columns, dtype=torch.bool, device=self.device)
        predicted_cols[predicted_ids // cpc] = True
        predicted_cols &= col_on
        bursting = col_on & ~predicted_cols
        correct_ids = torch.unique(predicted_ids[predicted_cols[predicted_ids // cpc]])  # sorted
        burst_cols = torch.nonzero(bursting).flatten()
        burst_ids = (burst_cols[:, None] * cpc + torch.arange(cpc, device=self.device)).flatten()
        active_ids = torch.sort(torch.cat([correct_ids, burst_ids])).values  # disjoint: their columns differ
        active = torch.zeros(self.cells, dtype=torch.bool, device=self.device)
        active[active_ids] = True
        best = self._best_matching(seg, seg_match & bursting[seg_col], seg_col, n_pot, burst_cols)  # index in seg
        matched = best >= 0
        winners_burst = torch.where(matched, seg_cell[best.clamp(min=0)] if seg.numel() else best, -1)
        least = self._least_used(burst_cols[~matched])
        winners_burst = winners_burst.clone()
        winners_burst[~matched] = least
        winners = torch.sort(torch.cat([correct_ids, winners_burst])).values
        if learn:
            learning = seg_active & predicted_cols[seg_col]
            learning[best[matched]] = True
            punished = seg[seg_match & ~col_on[seg_col]]
            self._learn(padded, seg[learning], n_pot[learning], punished, least)
        self.prev_active = active
        self._active_ids = (active, active_ids)
        self.prev_winners = winners
        self.step_count += 1
        return active_ids, winners

    def _indexed_activity(self, padded: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Return (segments with a synapse to a′, ascending; their numActivePotential; their connected count).

        Counted over a′'s synapses alone (:class:`SynapseIndex`) instead of every slot of every segment
        (:meth:`synapse_activity`): a step costs the active cells' fan-out, not the pool's size. With a threshold
        below 1 a segment without such a synapse could match, so then every segment is returned.
        """
        g, m = self.segments, self.cfg.max_synapses_per_segment
        pre = self.syn_pre[:g].reshape(-1)
        if self.index.due():
            self.index.rebuild(pre)
        held, ids = self._active_ids
        if held is not self.prev_active:  # a′ replaced from outside (a restore, a sequence reset)
            ids = torch.nonzero(self.prev_active).flatten()
            self._active_ids = (self.prev_active, ids)
        slots = self.index.active_slots(pre, ids, padded)
        strong = self.syn_perm[:g].reshape(-1)[slots] >= self.cfg.connected_permanence
        if min(self.cfg.min_threshold, self.cfg.activation_threshold) < 1:
            segment = slots // m
            every = torch.arange(g, device=self.device)
            return every, torch.bincount(segment, minlength=g), torch.bincount(segment[strong], minlength=g)
        seg, where = torch.unique(slots // m, return_inverse=True)  # slots ascending: so are their segments
        n_pot = torch.bincount(where, minlength=seg.numel())
        connected = torch.bincount(where[strong], minlength=seg.numel())
        return seg, n_pot, connected

    def _best_matching(
        self, seg: torch.Tensor, candidate: torch.Tensor, seg_col: torch.Tensor, n_pot: torch.Tensor,
        burst_cols: torch.Tensor,
    ) -> torch.Tensor:
        """Return, per bursting column, the index in ``seg`` of its best matching segment, or −1.

        Best: the most potential synapses, then the oldest, among the ``candidate`` ones.
        """
        g = self.segments
        if seg.numel() == 0:
            return torch.full((burst_cols.numel(),), -1, dtype=torch.int64, device=self.device)
        key = torch.where(candidate, n_pot * (g + 1) + (g - 1 - seg), -1)
        best = torch.full((self.cfg.columns,), -1, dtype=torch.int64, device=self.device)
        best.scatter_reduce_(0, seg_col, key, reduce="amax", include_self=True)
        chosen = best[burst_cols]
        return torch.where(chosen >= 0, torch.searchsorted(seg, (g - 1) - chosen % (g + 1)), -1)

    def _least_used(self, cols: torch.Tensor) -> torch.Tensor:
        """Return the least-used cell of each column in ``cols`` (fewest segments; hashed tie-break)."""
        cpc = self.cfg.cells_per_column
        if cols.numel() == 0:
            return torch.empty(0, dtype=torch.int64, device=self.device)
        counts = self._cell_segments.view(-1, cpc)[cols]
        shift = ((cols * HASH_A) ^ (self.step_count * HASH_B)) % cpc
        tie = (torch.arange(cpc, device=self.device)[None, :] + shift[:, None]) % cpc
        return cols * cpc + torch.argmin(counts * cpc + tie, dim=1)

    def _learn(
        self, padded: torch.Tensor, learning: torch.Tensor, learning_pot: torch.Tensor, punished: torch.Tensor,
        new_cells: torch.Tensor,
    ) -> None:
        """Reinforce the ``learning`` segments, punish the ``punished`` ones, grow synapses and new segments.

        ``learning``: ascending segment ids, ``learning_pot`` their numActivePotential; ``punished``: matching
        segments of inactive columns (``predicted_segment_decrement``); ``new_cells``: cells given a new segment.
        """
        cfg = self.cfg
        rows = learning
        is_learning = torch.ones(rows.numel(), dtype=torch.bool, device=self.device)
        if cfg.predicted_segment_decrement > 0:
            rows = torch.unique(torch.cat([learning, punished]))
            is_learning = torch.isin(rows, learning)
        if rows.numel():  # only these segments change: a few per step
            pre = torch.index_select(self.syn_pre, 0, rows)
            perm = torch.index_select(self.syn_perm, 0, rows)
            act = torch.take(padded, pre)  # these segments' synapses to a′
            delta = torch.where(act, cfg.permanence_increment, -cfg.permanence_decrement).to(torch.float32)
            if cfg.predicted_segment_decrement > 0:
                only_punished = (~is_learning)[:, None]
                delta = torch.where(only_punished & act, -cfg.predicted_segment_decrement, delta)
                delta = torch.where(only_punished & ~act, 0.0, delta)
            exists = pre >= 0
            perm = torch.where(exists, (perm + delta).clamp(0.0, 1.0), perm)
            pre = torch.where(exists & (perm <= 0.0), -1, pre)
            self.syn_perm.index_copy_(0, rows, perm)
            self.syn_pre.index_copy_(0, rows, pre)
        if self.prev_winners.numel() == 0:
            return
        want = (cfg.max_new_synapse_count - learning_pot).clamp(min=0)
        new_segs = self._new_segments(new_cells)
        grow_segs = torch.cat([learning, new_segs])
        want = torch.cat([want, torch.full_like(new_segs, cfg.max_new_synapse_count)])
        self._grow(grow_segs, want)

    def _new_segments(self, cells: torch.Tensor) -> torch.Tensor:
        """Append one empty segment per cell; return their ids."""
        n = cells.numel()
        start = self.segments
        need = start + n
        if need > self.seg_cell.numel():
            capacity = max(need, 2 * self.seg_cell.numel(), 256)
            m = self.cfg.max_synapses_per_segment
            seg_cell = torch.full((capacity,), 0, dtype=torch.int64, device=self.device)
            syn_pre = torch.full((capacity, m), -1, dtype=torch.int64, device=self.device)
            syn_perm = torch.zeros((capacity, m), dtype=torch.float32, device=self.device)
            seg_cell[:start] = self.seg_cell[:start]
            syn_pre[:start] = self.syn_pre[:start]
            syn_perm[:start] = self.syn_perm[:start]
            self.seg_cell, self.syn_pre, self.syn_perm = seg_cell, syn_pre, syn_perm
        self.seg_cell[start:need] = cells
        self._cell_segments.index_add_(0, cells, torch.ones_like(cells))
        self.syn_pre[start:need] = -1
        self.syn_perm[start:need] = 0.0
        self.segments = need
        return torch.arange(start, need, dtype=torch.int64, device=self.device)

    def _grow(self, segs: torch.Tensor, want: torch.Tensor) -> None:
        """Give each segment up to ``want`` new synapses to previous winners it lacks (hash order of winners)."""
        if segs.numel() == 0:
            return
        w = self.prev_winners
        w = w[torch.argsort((w * HASH_A + self.step_count * HASH_B) % (1 << 31), stable=True)]
        pre = self.syn_pre[segs]
        present = (pre[:, :, None] == w[None, None, :]).any(dim=1)
        avail = ~present
        rank = torch.cumsum(avail.to(torch.int64), dim=1) - 1
        chosen = avail & (rank < want[:, None])
        key = torch.where(pre < 0, -1.0, self.syn_perm[segs])
        slot_order = torch.sort(key, dim=1, stable=True).indices
        r, j = torch.nonzero(chosen, as_tuple=True)
        slot = slot_order[r, rank[r, j]]
        self.syn_pre[segs[r], slot] = w[j]
        self.syn_perm[segs[r], slot] = self.cfg.initial_permanence
        self.index.wrote(segs[r] * self.cfg.max_synapses_per_segment + slot)

    # -------------------------------------------------------------- snapshot
    def snapshot(self, prefix: str = "tm_") -> dict[str, np.ndarray]:
        """Return the state as arrays: the segment pool (used part), a′ and the previous winners."""
        g = self.segments
        return {
            prefix + "seg_cell": self.seg_cell[:g].cpu().numpy().astype(np.int64),
            prefix + "syn_pre": self.syn_pre[:g].cpu().numpy().astype(np.int32),
            prefix + "syn_perm": self.syn_perm[:g].cpu().numpy().copy(),
            prefix + "prev_active": torch.nonzero(self.prev_active).flatten().cpu().numpy().astype(np.int64),
            prefix + "prev_winners": self.prev_winners.cpu().numpy().astype(np.int64),
            prefix + "step": np.asarray(self.step_count, dtype=np.int64),
        }

    def load(self, state: Mapping[str, np.ndarray], prefix: str = "tm_") -> None:
        """Overwrite the state with :meth:`snapshot` arrays, exactly."""
        m = self.cfg.max_synapses_per_segment
        cells = torch.from_numpy(np.array(state[prefix + "seg_cell"], dtype=np.int64)).reshape(-1)
        self.segments = 0
        self._cell_segments = torch.zeros(self.cells, dtype=torch.int64, device=self.device)
        self.seg_cell = torch.empty(0, dtype=torch.int64, device=self.device)
        self.syn_pre = torch.empty((0, m), dtype=torch.int64, device=self.device)
        self.syn_perm = torch.empty((0, m), dtype=torch.float32, device=self.device)
        ids = self._new_segments(cells.to(self.device))
        pre = np.array(state[prefix + "syn_pre"], np.int64).reshape(-1, m)
        perm = np.array(state[prefix + "syn_perm"], np.float32).reshape(-1, m)
        self.syn_pre[ids] = torch.from_numpy(pre).to(self.device)
        self.syn_perm[ids] = torch.from_numpy(perm).to(self.device)
        self.index = SynapseIndex(self.cells, self.device)
        self.load_sequence(state, prefix)

    def sequence_snapshot(self, prefix: str = "tm_") -> dict[str, IntArray]:
        """Return the sequence state alone (a′, the previous winners, the step), not the learnt segments."""
        return {
            prefix + "prev_active": torch.nonzero(self.prev_active).flatten().cpu().numpy().astype(np.int64),
            prefix + "prev_winners": self.prev_winners.cpu().numpy().astype(np.int64),
            prefix + "step": np.asarray(self.step_count, dtype=np.int64),
        }

    def load_sequence(self, state: Mapping[str, np.ndarray], prefix: str = "tm_") -> None:
        """Overwrite the sequence state with :meth:`sequence_snapshot` arrays."""
        self.prev_active = torch.zeros(self.cells, dtype=torch.bool, device=self.device)
        self.prev_active[torch.from_numpy(np.array(state[prefix + "prev_active"], np.int64)).to(self.device)] = True
        self.prev_winners = torch.from_numpy(np.array(state[prefix + "prev_winners"], np.int64)).to(self.device)
        self.step_count = int(state[prefix + "step"])

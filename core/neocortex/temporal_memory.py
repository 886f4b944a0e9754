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

import numpy as np
import torch

HASH_A = 2654435761  # Knuth's multiplicative hash constant
HASH_B = 40503


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

    # ------------------------------------------------------------------ step
    def synapse_activity(self) -> torch.Tensor:
        """Return the (G, M) bool mask of synapses whose presynaptic cell is in a′."""
        pre = self.syn_pre[: self.segments]
        padded = torch.cat([self.prev_active, self._no_cell])  # an empty slot (−1) reads the False at the end
        return torch.take(padded, pre)

    def segment_activity(self, pre_act: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Return (active (G,), matching (G,), numActivePotential (G,)) of every segment against a′."""
        pre_act = self.synapse_activity() if pre_act is None else pre_act
        perm = self.syn_perm[: self.segments]
        connected = (pre_act & (perm >= self.cfg.connected_permanence)).sum(dim=1, dtype=torch.int32)
        potential = pre_act.sum(dim=1, dtype=torch.int32).to(torch.int64)
        return connected >= self.cfg.activation_threshold, potential >= self.cfg.min_threshold, potential

    def predicted_cells(self) -> torch.Tensor:
        """Return the (cells,) bool mask of cells with an active segment (predicted for the next step)."""
        active, _, _ = self.segment_activity()
        mask = torch.zeros(self.cells, dtype=torch.bool, device=self.device)
        mask[self.seg_cell[: self.segments][active]] = True
        return mask

    def compute(self, active_columns: torch.Tensor, learn: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """Advance one step; return (active cells, winner cells), both sorted int64 cell ids."""
        cfg = self.cfg
        cpc = cfg.cells_per_column
        g = self.segments
        pre_act = self.synapse_activity()
        seg_active, seg_match, n_pot = self.segment_activity(pre_act)
        seg_cell = self.seg_cell[:g]
        seg_col = seg_cell // cpc
        col_on = torch.zeros(cfg.columns, dtype=torch.bool, device=self.device)
        col_on[active_columns.to(self.device)] = True
        # in cell ids, not masks over every cell: a step touches the few active columns' cells
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
        best_seg = self._best_matching(seg_match, seg_col, n_pot, bursting, burst_cols)
        matched = best_seg >= 0
        winners_burst = torch.where(matched, seg_cell[best_seg.clamp(min=0)] if g else best_seg, -1)
        unmatched_cols = burst_cols[~matched]
        least = self._least_used(unmatched_cols)
        winners_burst = winners_burst.clone()
        winners_burst[~matched] = least
        winners = torch.sort(torch.cat([correct_ids, winners_burst])).values
        if learn:
            learning = seg_active & predicted_cols[seg_col]
            learning[best_seg[matched]] = True
            self._learn(pre_act, learning, n_pot, seg_match & ~col_on[seg_col], least)
        self.prev_active = active
        self.prev_winners = winners
        self.step_count += 1
        return active_ids, winners

    def _best_matching(
        self, seg_match: torch.Tensor, seg_col: torch.Tensor, n_pot: torch.Tensor, bursting: torch.Tensor,
        burst_cols: torch.Tensor,
    ) -> torch.Tensor:
        """Return, per bursting column, its best matching segment (most potential synapses, oldest) or −1."""
        g = self.segments
        if g == 0:
            return torch.full((burst_cols.numel(),), -1, dtype=torch.int64, device=self.device)
        candidate = seg_match & bursting[seg_col]
        key = torch.where(candidate, n_pot * (g + 1) + (g - 1 - torch.arange(g, device=self.device)), -1)
        best = torch.full((self.cfg.columns,), -1, dtype=torch.int64, device=self.device)
        best.scatter_reduce_(0, seg_col, key, reduce="amax", include_self=True)
        chosen = best[burst_cols]
        return torch.where(chosen >= 0, (g - 1) - chosen % (g + 1), -1)

    def _least_used(self, cols: torch.Tensor) -> torch.Tensor:
        """Return the least-used cell of each column in ``cols`` (fewest segments; hashed tie-break)."""
        cpc = self.cfg.cells_per_column
        if cols.numel() == 0:
            return torch.empty(0, dtype=torch.int64, device=self.device)
        counts = torch.bincount(self.seg_cell[: self.segments], minlength=self.cells).view(-1, cpc)[cols]
        shift = ((cols * HASH_A) ^ (self.step_count * HASH_B)) % cpc
        tie = (torch.arange(cpc, device=self.device)[None, :] + shift[:, None]) % cpc
        return cols * cpc + torch.argmin(counts * cpc + tie, dim=1)

    def _learn(
        self, pre_act: torch.Tensor, learning: torch.Tensor, n_pot: torch.Tensor, punished: torch.Tensor,
        new_cells: torch.Tensor,
    ) -> None:
        cfg = self.cfg
        touched = learning | punished if cfg.predicted_segment_decrement > 0 else learning
        rows = torch.nonzero(touched).flatten()  # only these segments change: a few per step
        if rows.numel():
            pre = torch.index_select(self.syn_pre, 0, rows)
            perm = torch.index_select(self.syn_perm, 0, rows)
            act = torch.index_select(pre_act, 0, rows)
            delta = torch.where(act, cfg.permanence_increment, -cfg.permanence_decrement).to(torch.float32)
            if cfg.predicted_segment_decrement > 0:
                hit = (punished[rows] & ~learning[rows])[:, None] & act
                delta = torch.where(hit, -cfg.predicted_segment_decrement, delta)
                delta = torch.where((punished[rows] & ~learning[rows])[:, None] & ~act, 0.0, delta)
            exists = pre >= 0
            perm = torch.where(exists, (perm + delta).clamp(0.0, 1.0), perm)
            pre = torch.where(exists & (perm <= 0.0), -1, pre)
            self.syn_perm.index_copy_(0, rows, perm)
            self.syn_pre.index_copy_(0, rows, pre)
        if self.prev_winners.numel() == 0:
            return
        grow_segs = torch.nonzero(learning).flatten()
        want = (cfg.max_new_synapse_count - n_pot[grow_segs]).clamp(min=0)
        new_segs = self._new_segments(new_cells)
        grow_segs = torch.cat([grow_segs, new_segs])
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
        self.seg_cell = torch.empty(0, dtype=torch.int64, device=self.device)
        self.syn_pre = torch.empty((0, m), dtype=torch.int64, device=self.device)
        self.syn_perm = torch.empty((0, m), dtype=torch.float32, device=self.device)
        ids = self._new_segments(cells.to(self.device))
        pre = np.array(state[prefix + "syn_pre"], np.int64).reshape(-1, m)
        perm = np.array(state[prefix + "syn_perm"], np.float32).reshape(-1, m)
        self.syn_pre[ids] = torch.from_numpy(pre).to(self.device)
        self.syn_perm[ids] = torch.from_numpy(perm).to(self.device)
        self.load_sequence(state, prefix)

    def sequence_snapshot(self, prefix: str = "tm_") -> dict[str, np.ndarray]:
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

"""HTM Spatial Pooler on torch tensors (thesis Table 3.2 data structures, Table 4.1/5.1 values).

Columns sit on a ring of ``columns`` positions, inputs on a ring of ``inputs`` positions; column c's
centre is input ⌊(c + ½)·inputs/columns⌋ and its potential pool is a fixed ``potential_pct`` share
(seeded draw) of the inputs within ``potential_radius`` of the centre (wrapping). Initial permanences of
the pool are uniform in [connected − 0.1, connected + 0.1] (about half connected), outside the pool 0.

Per input x (bool, ``inputs``):

* overlap(c) = #{i : x_i ∧ perm(c, i) ≥ connected}, then ``overlap < stimulus`` → 0;
* boosted = overlap · boost(c) with boost(c) = exp(−β·(activeDuty(c) − target)), target = w/columns;
* global inhibition: the w columns with the largest boosted overlap (ties: lower column index),
  columns with zero overlap never win;
* learning (winners only): perm += inc on active pool inputs, −= dec on inactive pool inputs, clipped
  to [0, 1]; duty cycles are moving averages over ``duty_cycle_period`` steps.

Everything is exact integer counting or elementwise float32 arithmetic, so results do not depend on
the thread count. On the CPU the connected synapses are kept as bit rows (64 inputs a word) and an overlap
is the popcount of a row AND the input's bits: the same integers as summing the connected rows of the active
inputs (which a GPU does), from 512 KB instead of a 16 MB float matrix at 2048 × 2048.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import cast

import numpy as np
import torch

from core.arrays import BoolArray, IntArray, UInt8Array, UInt64Array
from core.neocortex.lsbh import digest


class SpatialPooler:
    """A global-inhibition spatial pooler whose whole state is a few dense tensors."""

    def __init__(
        self,
        inputs: int,
        columns: int,
        active: int,
        *,
        potential_radius: int,
        potential_pct: float,
        connected: float,
        inc: float,
        dec: float,
        boost_strength: float = 0.0,
        duty_cycle_period: int = 1000,
        stimulus_threshold: int = 0,
        seed: int = 42,
        device: torch.device | str = "cpu",
    ) -> None:
        self.inputs, self.columns, self.active = inputs, columns, active
        self.connected, self.inc, self.dec = connected, inc, dec
        self.boost_strength, self.period, self.stimulus = boost_strength, duty_cycle_period, stimulus_threshold
        self.device = torch.device(device)
        pool = (inputs, columns, potential_radius, potential_pct, connected, seed)
        potential, perm = initial_pools(*pool)
        _, _, pool_digest, pool_index = _drawn_pools(*pool)
        self.pool_digest = pool_digest.copy()
        """SHA-256 of the potential pools (float32 bytes), checked when a snapshot is loaded."""
        self.potential = potential.to(self.device)
        self._pool_ids = (self.potential, pool_index.to(self.device))  # (pool, its flat ids): see pool_ids
        self.permanence = perm.to(self.device)
        self._bits = self.device.type == "cpu"  # connected synapses as bit rows (popcount overlaps)
        self._connected_bits = np.zeros((0, 0), dtype=np.uint64)
        self._connected_t = torch.zeros(0)
        self.sync_connected()
        self.active_duty = torch.zeros(columns, dtype=torch.float32, device=self.device)
        self.overlap_duty = torch.zeros(columns, dtype=torch.float32, device=self.device)
        self.iteration = 0

    def sync_connected(self) -> None:
        """Rebuild the connected-synapse structure from :attr:`permanence` (after it is set wholesale)."""
        connected = self.permanence >= self.connected
        if self._bits:
            self._connected_bits = pack_rows(connected.numpy())
        else:
            self._connected_t = connected.to(torch.float32).T.contiguous()  # (inputs, columns)

    def overlaps(self, x: torch.Tensor) -> torch.Tensor:
        """Return the (columns,) overlap counts of bool input ``x`` with each column's connected synapses.

        CPU: the popcount of each column's connected bits AND the input's. Elsewhere: the sum of the
        connected-synapse rows of the active inputs, in float32 over 0/1 values: every partial sum is an integer
        < 2²⁴, so exact in any order. The same integers either way.
        """
        if self._bits:
            words = pack_rows(x.cpu().numpy().reshape(1, -1))
            counts = torch.from_numpy(popcount_rows(self._connected_bits & words))
        else:
            active = torch.nonzero(x.to(self.device)).flatten()
            counts = torch.index_select(self._connected_t, 0, active).sum(dim=0).to(torch.int64)
        return torch.where(counts >= self.stimulus, counts, torch.zeros_like(counts))

    def boost(self) -> torch.Tensor:
        """Return the (columns,) boost factors exp(−β·(activeDuty − w/columns)); all 1 when β = 0."""
        if self.boost_strength == 0:
            return torch.ones(self.columns, dtype=torch.float32, device=self.device)
        target = self.active / self.columns
        return torch.exp(-self.boost_strength * (self.active_duty - target))

    def inhibit(self, scores: torch.Tensor) -> torch.Tensor:
        """Return the sorted indices of the ``active`` best-scoring columns with a score > 0 (ties: lower index)."""
        order = torch.sort(scores, descending=True, stable=True).indices[: self.active]
        winners = order[scores[order] > 0]
        return torch.sort(winners).values

    def compute(self, x: torch.Tensor, learn: bool = True) -> torch.Tensor:
        """Return the active columns (sorted int64) for input ``x`` and, with ``learn``, adapt the pools."""
        overlap = self.overlaps(x)
        winners = self.inhibit(overlap.to(torch.float32) * self.boost())
        if learn:
            self._learn(x.to(self.device), winners, overlap)
        return winners

    def _learn(self, x: torch.Tensor, winners: torch.Tensor, overlap: torch.Tensor) -> None:
        old = torch.index_select(self.permanence, 0, winners)
        pool = torch.index_select(self.potential, 0, winners)
        delta = torch.where(x[None, :], self.inc, -self.dec).to(torch.float32)
        rows = torch.where(pool, (old + delta).clamp_(0.0, 1.0), old)
        self.permanence.index_copy_(0, winners, rows)
        now = rows >= self.connected
        if self._bits:
            self._connected_bits[winners.numpy()] = pack_rows(now.numpy())
        else:
            r, i = torch.nonzero(now != (old >= self.connected), as_tuple=True)  # synapses that (dis)connected
            self._connected_t[i, winners[r]] = now[r, i].to(torch.float32)
        self.iteration += 1
        period = float(min(self.period, self.iteration))
        fired = torch.zeros(self.columns, dtype=torch.float32, device=self.device)
        fired[winners] = 1.0
        self.active_duty = (self.active_duty * (period - 1.0) + fired) / period
        overlapped = (overlap > 0).to(torch.float32)
        self.overlap_duty = (self.overlap_duty * (period - 1.0) + overlapped) / period

    # -------------------------------------------------------------- snapshot
    def pool_ids(self) -> torch.Tensor:
        """Return the flat ids (row-major, ascending) of :attr:`potential`'s synapses: its mask's order.

        Kept from the pools' draw; found again when :attr:`potential` is replaced (a gather by ids reads 1.2 M
        of 4 M permanences in a tenth of a masked select's time).
        """
        pool, ids = self._pool_ids
        if pool is not self.potential:
            ids = torch.nonzero(self.potential.reshape(-1)).flatten()
            self._pool_ids = (self.potential, ids)
        return ids

    def snapshot(self, prefix: str = "sp_") -> dict[str, np.ndarray]:
        """Return the learnt state: the pool's permanences (row-major order of the seeded pool mask) and duties."""
        return {
            prefix + "permanence": self.permanence.view(-1).index_select(0, self.pool_ids()).cpu().numpy(),
            prefix + "pool_digest": self.pool_digest.copy(),
            prefix + "active_duty": self.active_duty.cpu().numpy().copy(),
            prefix + "overlap_duty": self.overlap_duty.cpu().numpy().copy(),
            prefix + "iteration": np.asarray(self.iteration, dtype=np.int64),
        }

    def load(self, state: Mapping[str, np.ndarray], prefix: str = "sp_") -> None:
        """Overwrite the learnt state with :meth:`snapshot` arrays, exactly."""
        values = torch.from_numpy(np.array(state[prefix + "permanence"], dtype=np.float32)).reshape(-1)
        same_pool = np.array_equal(state[prefix + "pool_digest"], self.pool_digest)
        ids = self.pool_ids()
        if values.numel() != ids.numel() or not same_pool:
            msg = "the stored spatial pooler does not fit the potential pools regenerated from its seed"
            raise ValueError(msg)
        perm = torch.zeros((self.columns, self.inputs), dtype=torch.float32, device=self.device)
        perm.view(-1).index_copy_(0, ids, values.to(self.device))  # perm[potential] = values
        self.permanence = perm
        self.sync_connected()
        self.active_duty = torch.from_numpy(np.array(state[prefix + "active_duty"], np.float32)).to(self.device)
        self.overlap_duty = torch.from_numpy(np.array(state[prefix + "overlap_duty"], np.float32)).to(self.device)
        self.iteration = int(state[prefix + "iteration"])


def pack_rows(rows: BoolArray) -> UInt64Array:
    """Return bool rows (n, m) as bits, 64 to a word: (n, ⌈m/64⌉) uint64 (zero-padded; any fixed bit order)."""
    rows = np.asarray(rows, dtype=bool)
    pad = (-rows.shape[1]) % 64
    if pad:
        rows = np.concatenate([rows, np.zeros((rows.shape[0], pad), dtype=bool)], axis=1)
    return np.ascontiguousarray(np.packbits(rows, axis=1, bitorder="little")).view(np.uint64)


_BYTE_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)


def popcount_rows(words: UInt64Array) -> IntArray:
    """Return the number of set bits of each row of (n, w) uint64 words, int64 (n,)."""
    if hasattr(np, "bitwise_count"):  # numpy ≥ 2
        return cast(IntArray, np.bitwise_count(words).sum(axis=1, dtype=np.int64))
    return cast(  # pragma: no cover (numpy 1.26)
        IntArray, _BYTE_POPCOUNT[words.view(np.uint8)].sum(axis=1, dtype=np.int64)
    )


def initial_pools(
    inputs: int, columns: int, radius: int, pct: float, connected: float, seed: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Return (potential (columns, inputs) bool, permanence float32) as described in the module docstring.

    Drawn once per argument set and copied after (a session builds several poolers from one seed: its
    own, each candidate map's reader, a merged or restored one; 0.3 s a draw at 2048 × 2048).
    """
    potential, perm, _, _ = _drawn_pools(inputs, columns, radius, pct, connected, seed)
    return potential.clone(), perm.clone()


@functools.lru_cache(maxsize=2)
def _drawn_pools(
    inputs: int, columns: int, radius: int, pct: float, connected: float, seed: int
) -> tuple[torch.Tensor, torch.Tensor, UInt8Array, torch.Tensor]:
    """Return (potential, permanence, the potential's digest, its flat ids) of one argument set.

    Cached: never modify them. The flat ids (int64, ascending) are the row-major order of
    ``permanence[potential]``, so a snapshot gathers and a restore scatters the pool's permanences by them.
    """
    generator = torch.Generator(device="cpu").manual_seed(int(seed))
    centre = ((torch.arange(columns, dtype=torch.float64) + 0.5) * inputs / columns).floor().to(torch.int32)
    offset = (torch.arange(inputs, dtype=torch.int32)[None, :] - centre[:, None]).remainder_(inputs)
    near = (offset <= radius) | (offset >= inputs - radius)  # ring distance min(o, n − o) ≤ radius
    draw = torch.rand((columns, inputs), generator=generator, dtype=torch.float32)
    potential = near & (draw < pct)
    start = torch.rand((columns, inputs), generator=generator, dtype=torch.float32)
    perm = ((connected - 0.1) + 0.2 * start).clamp_(0.0, 1.0).mul_(potential)  # ≥ 0: outside the pool +0.0
    return potential, perm, digest(potential.to(torch.float32)), torch.nonzero(potential.view(-1)).flatten()

"""Spatial-view cells from SDRs and HTM: the engine's second view module (``frontend = "sdr-htm"``).

Per frame (PoseidonSLAM §4.2.2): embedding y (Eq. 4.1) → LSBH SDR (Eq. 4.2) → OR fusion (Eq. 4.3; one
camera modality here) → spatial pooler → temporal memory → winner cells → descriptor D_t (pooling,
interval union, top-k cap; Eqs 4.4–4.5) → overlap match against the prototypes (Eqs 4.6–4.9) → the
matched id, or a new view cell whose prototype is D_t (Eq. 4.10). The interface is the one of
:class:`core.localview.LocalViewCells`: ``process(image) -> (id, relative_rad, created)``, ``count``,
``current``/``previous``, ``snapshot``/``restore``; relative_rad is always 0 (SDRs carry no shift).

Snapshot: the prototypes are the ``lv_templates`` rows, float32 (N, 1, topk) holding cell ids (exact:
ids < 2²⁴) padded with −1, ``lv_means`` their sizes, so the store, archives and merges treat them as
templates. ``lv_sdr`` (N, L/8) uint8 keeps each view cell's *code*: the packed fused SDR (Eq. 4.3) of the
frame that made it. Unlike a prototype it does not depend on what the pooler learnt (the projection is
fixed and seeded), so another session's frames can be compared with it (the merge's observations,
``mapserver.merge.cortex``); a snapshot made before the key existed restores with zero codes.
The projection (``nc_projection``, or for CNN embeddings too big to store its SHA-256
``nc_projection_digest``, checked on restore), the pooler (``nc_sp_*``), the temporal memory
(``nc_tm_*``) and the descriptor's window (``nc_history*``, ``nc_run``) are plain arrays too.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
import torch

from core.arrays import IntArray, UInt8Array
from core.neocortex.descriptor import Match, MatchGates, best_match, cap_topk, interval_length
from core.neocortex.encoder import Encoder, resolve_device
from core.neocortex.lsbh import digest, fuse, lsbh_bits, projection, projection_digest
from core.neocortex.spatial_pooler import SpatialPooler
from core.neocortex.temporal_memory import TemporalMemory, TMConfig

if TYPE_CHECKING:
    from core.config import Params

STORED_PROJECTION_MAX = 1 << 22  # projections up to 4 Mi entries (16 MB) are stored; larger ones by digest
FLOAT32_EXACT = 1 << 24
SONAR_SEED = 1000  # the sonar modality's projection: seed lsbh_seed + SONAR_SEED (the camera's: lsbh_seed)


class NeocortexViewCells:
    """SDR + HTM view cells with prototype matching by overlap recall."""

    def __init__(self, params: Params) -> None:
        self.params = params
        self.device = resolve_device(params.frontend_device)
        if self.device.type == "cpu":
            torch.set_num_threads(1)  # small tensors: intra-op threads only add contention (as the pipeline's BLAS)
        self.encoder = Encoder(params, self.device)
        half = params.lsbh_bits // 2
        self.k = int(params.lsbh_s * half)
        self.projection = projection(self.encoder.dims, half, params.lsbh_seed).to(self.device)
        self.projection_digest = projection_digest(self.encoder.dims, half, params.lsbh_seed)
        """:func:`~core.neocortex.lsbh.digest` of :attr:`projection` (kept with it: the matrix never changes)."""
        self.sonar_projection: torch.Tensor | None = None
        self.sp = SpatialPooler(
            params.lsbh_bits, params.sp_columns, params.sp_num_active_columns,
            potential_radius=params.sp_potential_radius, potential_pct=params.sp_potential_pct,
            connected=params.sp_syn_perm_connected, inc=params.sp_syn_perm_active_inc,
            dec=params.sp_syn_perm_inactive_dec, boost_strength=params.sp_boost_strength,
            duty_cycle_period=params.sp_duty_cycle_period, seed=params.lsbh_seed + 1, device=self.device,
        )
        self.tm = TemporalMemory(tm_config(params), self.device)
        if self.tm.cells >= FLOAT32_EXACT:
            msg = f"sp_columns × tm_cells_per_column = {self.tm.cells} cells: prototypes need < 2^24"
            raise ValueError(msg)
        self.gates = MatchGates(params.sv_min_intersection, params.sv_tm_match_threshold,
                                params.sv_enable_f1_gate, params.min_f1, params.sv_use_iou_tiebreak)
        self.history: list[np.ndarray] = []
        self.run = 0
        self._prototypes = np.empty((0, params.sv_tm_topk), dtype=np.int64)
        self._sizes = np.empty(0, dtype=np.int64)
        self._codes = np.empty((0, code_bytes(params.lsbh_bits)), dtype=np.uint8)
        self.current = -1
        self.previous = -1
        self.relative_rad = 0.0
        self.last_view: IntArray | None = None
        self.last_mean = 0.0
        self.last_match: Match | None = None
        self.last_code: UInt8Array | None = None
        """The packed fused SDR (L/8 uint8) of the last frame processed or read."""

    @property
    def count(self) -> int:
        """Return the number of view cells (prototypes)."""
        return int(self._sizes.size)

    @property
    def prototypes(self) -> tuple[IntArray, IntArray]:
        """Return (cells (N, topk) int64 padded −1, sizes (N,))."""
        return self._prototypes, self._sizes

    @property
    def codes(self) -> UInt8Array:
        """Return every view cell's code: (N, L/8) uint8, the packed SDR of the frame that made it (0: unknown)."""
        return self._codes

    def add_prototypes(self, cells: IntArray, sizes: np.ndarray, codes: UInt8Array | None = None) -> None:
        """Append prototypes (−1 padded rows of ``sv_tm_topk`` cell ids) with their sizes and codes (0: unknown)."""
        rows = np.asarray(cells, dtype=np.int64).reshape(-1, self.params.sv_tm_topk)
        width = code_bytes(self.params.lsbh_bits)
        packed = np.zeros((rows.shape[0], width), dtype=np.uint8)
        if codes is not None:
            given = np.asarray(codes, dtype=np.uint8).reshape(-1, width)[: rows.shape[0]]
            packed[: given.shape[0]] = given
        self._prototypes = np.concatenate([self._prototypes, rows])
        self._sizes = np.concatenate([self._sizes, np.asarray(sizes, dtype=np.int64).reshape(-1)])
        self._codes = np.concatenate([self._codes, packed])

    # ------------------------------------------------------------------ step
    def sdr(self, image: UInt8Array, sonar: UInt8Array | None = None) -> torch.Tensor:
        """Return the fused SDR (lsbh_bits,) bool of ``image`` and ``sonar`` (Eqs 4.1–4.3).

        Each modality has its own fixed projection P_m (the sonar's seeded ``lsbh_seed`` + ``SONAR_SEED``,
        made on its first image) and its own top/bottom-k bits; the SDRs are fused by bitwise OR.
        """
        bits = [lsbh_bits((self.encoder(image) @ self.projection)[0], self.k)]
        if sonar is not None:
            if self.sonar_projection is None:
                half = self.params.lsbh_bits // 2
                seed = self.params.lsbh_seed + SONAR_SEED
                self.sonar_projection = projection(self.encoder.dims, half, seed).to(self.device)
            bits.append(lsbh_bits((self.encoder(sonar) @ self.sonar_projection)[0], self.k))
        return fuse(bits)

    def _keep_code(self, image: UInt8Array, sonar: UInt8Array | None) -> torch.Tensor:
        """Return the frame's SDR (:meth:`sdr`) and keep it packed as :attr:`last_code`."""
        code = self.sdr(image, sonar)
        self.last_code = np.packbits(code.cpu().numpy())
        return code

    def descriptor(self, winners: IntArray) -> IntArray:
        """Push this step's winner cells and return D_t (see :mod:`core.neocortex.descriptor`)."""
        p = self.params
        if self.history and winners.size:
            shared = np.intersect1d(winners, self.history[-1], assume_unique=True).size
            self.run = self.run + 1 if shared / winners.size >= p.theta_alpha else 1
        else:
            self.run = 1
        self.history.append(winners)
        del self.history[: max(0, len(self.history) - p.sv_tm_window)]
        span = interval_length(self.run, p.sv_tm_window, p.theta_rho, p.interval_mode)
        return cap_topk(self.history[-span:], p.sv_tm_topk)

    def process(self, image: UInt8Array, sonar: UInt8Array | None = None) -> tuple[int, float, bool]:
        """Encode, pool, sequence and match ``image`` (and ``sonar``); return (view cell id, 0.0, created)."""
        columns = self.sp.compute(self._keep_code(image, sonar), learn=self.params.sp_learn)
        _, winners = self.tm.compute(columns, learn=True)
        source = columns if self.params.sv_descriptor_source == "sp" else winners  # sp: no sequence memory
        d = self.descriptor(source.cpu().numpy().astype(np.int64))
        match = best_match(d, self._prototypes, self._sizes, self.gates)
        self.last_view, self.last_mean, self.last_match = d, float(d.size), match
        self.previous = self.current
        if match is not None and match.accepted:
            self.current = match.index
            return match.index, 0.0, False
        row = np.full((1, self.params.sv_tm_topk), -1, dtype=np.int64)
        row[0, : d.size] = d
        assert self.last_code is not None  # kept by _keep_code
        self.add_prototypes(row, np.array([d.size]), self.last_code[None, :])
        self.current = self.count - 1
        return self.current, 0.0, True

    def read(self, image: UInt8Array, sonar: UInt8Array | None = None, code: UInt8Array | None = None) -> IntArray:
        """Return D_t of ``image`` through this cortex without learning and without making a view cell.

        Inference only (spatial pooler and temporal memory with learning off): a stored map's cortex reads
        another session's frames in its own cell space, so that its prototypes can be matched (the merge's
        observations, ``mapserver.merge.cortex``). The sequence state (active cells, winners, the descriptor
        window) advances as in :meth:`process`; the learnt state (permanences, segments) does not change.
        ``code``: the frame's packed SDR when another cortex with the same encoder and projection has made it
        already (the running session's, :attr:`last_code`): the frame is then not encoded again.
        """
        if code is None:
            sdr = self._keep_code(image, sonar)
        else:
            self.last_code = np.asarray(code, dtype=np.uint8).copy()
            sdr = torch.from_numpy(unpack_codes(self.last_code, self.params.lsbh_bits).astype(bool)).to(self.device)
        columns = self.sp.compute(sdr, learn=False)
        _, winners = self.tm.compute(columns, learn=False)
        source = columns if self.params.sv_descriptor_source == "sp" else winners
        d = self.descriptor(source.cpu().numpy().astype(np.int64))
        self.last_view, self.last_mean = d, float(d.size)
        return d

    def match(self, descriptor: IntArray) -> Match | None:
        """Return the best prototype for ``descriptor`` with the Eq. 4.9 verdict (no state change)."""
        return best_match(np.asarray(descriptor, dtype=np.int64), self._prototypes, self._sizes, self.gates)

    def match_among(self, descriptor: IntArray, ids: IntArray) -> Match | None:
        """Return :meth:`match`'s answer restricted to the prototypes ``ids`` (``index`` is a prototype id)."""
        ids = np.unique(np.asarray(ids, dtype=np.int64))
        found = best_match(np.asarray(descriptor, dtype=np.int64), self._prototypes[ids], self._sizes[ids], self.gates)
        if found is None:
            return None
        return Match(int(ids[found.index]), found.intersection, found.recall, found.f1, found.iou, found.accepted)

    # -------------------------------------------------------------- snapshot
    def snapshot(self) -> dict[str, np.ndarray]:
        """Return the whole front-end state as plain arrays (keys ``lv_*`` and ``nc_*``)."""
        state: dict[str, np.ndarray] = {
            "lv_templates": self._prototypes.astype(np.float32)[:, None, :],
            "lv_means": self._sizes.astype(np.float64),
            "lv_sdr": self._codes.copy(),
            "lv_current": np.asarray(self.current, dtype=np.int64),
            "lv_previous": np.asarray(self.previous, dtype=np.int64),
            "lv_relative_rad": np.asarray(self.relative_rad, dtype=np.float64),
            "nc_projection_digest": self.projection_digest.copy(),
            **self.sequence_state(),
        }
        if self.projection.numel() <= STORED_PROJECTION_MAX:
            state["nc_projection"] = self.projection.cpu().numpy().copy()
        if self.sonar_projection is not None:  # regenerated from the seed on restore, checked by its digest
            state["nc_sonar_projection_digest"] = digest(self.sonar_projection)
        state.update(self.sp.snapshot("nc_sp_"))
        state.update(self.tm.snapshot("nc_tm_"))
        return state

    def sequence_state(self) -> dict[str, IntArray]:
        """Return the state that changes from frame to frame in a cortex that does not learn.

        The TM's sequence state and the descriptor window: ``nc_tm_prev_*``, ``nc_tm_step``, ``nc_history*``,
        ``nc_run``.
        """
        history = np.full((self.params.sv_tm_window, max((h.size for h in self.history), default=0)), -1, np.int64)
        for i, h in enumerate(self.history):
            history[i, : h.size] = h
        return {
            "nc_history": history,
            "nc_history_len": np.asarray([h.size for h in self.history], dtype=np.int64),
            "nc_run": np.asarray(self.run, dtype=np.int64),
            **self.tm.sequence_snapshot("nc_tm_"),
        }

    def load_sequence_state(self, state: Mapping[str, np.ndarray]) -> None:
        """Overwrite the sequence state with :meth:`sequence_state` arrays."""
        history, lengths = np.asarray(state["nc_history"]), np.asarray(state["nc_history_len"])
        self.history = [history[i, : int(n)].astype(np.int64) for i, n in enumerate(lengths)]
        self.run = int(state["nc_run"])
        self.tm.load_sequence(state, "nc_tm_")

    @classmethod
    def restore(cls, params: Params, state: Mapping[str, np.ndarray]) -> NeocortexViewCells:
        """Rebuild the front-end from :meth:`snapshot` arrays so that it continues bit for bit."""
        cells = cls(params)
        if "nc_projection" in state:
            stored = torch.from_numpy(np.array(state["nc_projection"], dtype=np.float32))
            if tuple(stored.shape) != tuple(cells.projection.shape):
                msg = f"nc_projection has shape {tuple(stored.shape)}, expected {tuple(cells.projection.shape)}"
                raise ValueError(msg)
            regenerated = cells.projection.cpu().numpy()
            if not np.array_equal(stored.numpy().view(np.uint32), regenerated.view(np.uint32)):  # bits differ
                cells.projection = stored.to(cells.device)
                cells.projection_digest = digest(stored)
        if not np.array_equal(np.asarray(state["nc_projection_digest"]), cells.projection_digest):
            msg = "the stored LSBH projection differs from the one regenerated from lsbh_seed"
            raise ValueError(msg)
        if "nc_sonar_projection_digest" in state:
            half, seed = params.lsbh_bits // 2, params.lsbh_seed + SONAR_SEED
            cells.sonar_projection = projection(cells.encoder.dims, half, seed).to(cells.device)
            if not np.array_equal(np.asarray(state["nc_sonar_projection_digest"]), digest(cells.sonar_projection)):
                msg = "the stored sonar LSBH projection differs from the one regenerated from lsbh_seed"
                raise ValueError(msg)
        templates = np.asarray(state["lv_templates"], dtype=np.float32)
        cells.add_prototypes(
            templates.reshape(-1, params.sv_tm_topk).astype(np.int64), state["lv_means"], state.get("lv_sdr")
        )
        cells.current = int(state["lv_current"])
        cells.previous = int(state["lv_previous"])
        cells.relative_rad = float(state["lv_relative_rad"])
        cells.sp.load(state, "nc_sp_")
        cells.tm.load(state, "nc_tm_")
        cells.load_sequence_state(state)
        return cells


def code_bytes(bits: int) -> int:
    """Return the bytes of a packed SDR of ``bits`` bits (``np.packbits``: the last byte zero-padded)."""
    return (int(bits) + 7) // 8


def unpack_codes(packed: UInt8Array, bits: int) -> UInt8Array:
    """Return packed SDRs (…, ``code_bytes(bits)``) as 0/1 uint8 (…, ``bits``): the inverse of ``np.packbits``."""
    return np.unpackbits(np.asarray(packed, dtype=np.uint8), axis=-1)[..., : int(bits)]


def tm_config(params: Params) -> TMConfig:
    """Return the Temporal Memory configuration of ``params``."""
    return TMConfig(
        columns=params.sp_columns, cells_per_column=params.tm_cells_per_column,
        activation_threshold=params.tm_activation_threshold, min_threshold=params.tm_min_threshold,
        initial_permanence=params.tm_initial_permanence, connected_permanence=params.tm_connected_permanence,
        max_new_synapse_count=params.tm_max_new_synapse_count,
        max_synapses_per_segment=params.tm_max_synapses_per_segment,
        permanence_increment=params.tm_permanence_increment, permanence_decrement=params.tm_permanence_decrement,
        predicted_segment_decrement=params.tm_predicted_segment_decrement,
    )

"""Merge observations for maps of the ``sdr-htm`` front-end: the session's SDRs against the view cells' codes.

A view cell of the neocortical front-end (``core.neocortex``) is a set of its own temporal memory's
cells, and a spatial pooler that learnt on other frames maps the same image to other columns (measured
on ``cave3d``: after session 1, its pooler and session 2's agree on 35 % of the active columns for the
same image, median; matching session 2's descriptors against session 1's prototypes column by column
found no match at all). Two sessions' view cells are therefore not comparable through their prototypes.
What is comparable is the code they were made from: the LSBH SDR (Eqs 4.1–4.3, a fixed seeded projection,
no learning), which every view cell keeps (``lv_sdr``, the packed SDR of the frame that made it). An
**observation** is the frame's SDR matched against those codes: overlap recall R = |c ∩ c_ℓ| / |c| (Eq.
4.6 on codes), the best view cell accepted when R ≥ ``merge_sdr_min_overlap`` (ties to the lower id).
Measured with the weight-free encoder (session 2's frames against session 1's, ground truth): at the true
place (within 1.5 m and 15°) the best code overlaps 0.67–0.77 of the bits at the 10th percentile (``cave3d``
and ``symmetric`` the lower), at other places 0.41–0.62 at the 90th (look-alikes aside). The gate is a
calibration of the imagery: 0.68 by default (at 0.62 the approach to a straight copied street matched well
enough for 2 of 10 ``twin`` runs to merge falsely; none at 0.65 or 0.68), 0.62 in ``poseidon`` (at 0.68 the
cave's true merges fail on 9 of 10 seeds, at 0.62 none). ``merge_sdr_null_quantile`` (0.95 in ``poseidon``)
raises it per stored map to that quantile of the map's own look-alike overlaps (:func:`null_overlap`): a map
whose far places overlap as much as a street's gets a street's gate, a cave keeps its own (the gate each merge
passed is in its evidence, ``rule.sdr_min_overlap``). A miss then means what an LVC miss means, and the
sequential test and the probation weigh it as LVC's (``Params.miss_weight_reading``: 2). Before codes, the
stored map's cortex read the session (below) and its matches — p₁ = 0.4 — were the observations; a miss then
weighed 0.16 and a look-alike holding turns kept 2–4 false merges in 5 (README). Stored maps made before
``lv_sdr`` existed (zero codes) are still observed that way.

Each stored ``sdr-htm`` candidate map also gets a **reader**: its own cortex, restored from its snapshot and
stepped on every frame of the running session with learning off (:meth:`NeocortexViewCells.read`), so it
describes the session's frames in the map's own cells (sequence context included). The reader gives the
merged map one cortex: on a merge (Algorithm 1's operation (i) for SDR views) each of the partial map's view
cells gets the reader's descriptor at the frame that created it as its prototype
(:meth:`CortexReader.remember`), keeping its own code, and the merged engine continues in the reader's
cortex (the map's learnt state, the session's current sequence state) and learns from then on. For maps
without codes the reader's descriptor is matched against the map's prototypes (overlap recall R, I_min,
τ_R, F1, IoU: PoseidonSLAM Eqs 4.6–4.9) at the merge gates ``merge_sv_min_intersection`` (8) and
``merge_sv_enable_f1_gate`` (off). An accepted match is an observation like an LVC template match (error
reported so that "error ≤ threshold" means accepted; no heading offset), and the same hypotheses, evidence
test and probation decide and verify the merge (:mod:`mapserver.merge.online`).

Limits (stated in the README): a session joins at most one ``sdr-htm`` map (the first map's prototypes
were never read by a second map's cortex, so no bridge). Offline (``merge``, ``merge --redo``) there are no
frames: the partial map's view cells are compared by their codes (:mod:`mapserver.merge.offline_views`) and
re-expressed in the loaded cortex by reading those codes in creation order (:func:`translate_offline`).
A session stopped with ``--stop-after`` keeps its
readers' sequence state and translations with its merge driver's state (``MergerState.readers``), so it
resumes as one run; when a candidate map changed meanwhile, its readers and hypotheses restart instead.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from core.arrays import Float32Array, FloatArray, IntArray, UInt8Array
from core.neocortex.viewcells import NeocortexViewCells, code_bytes, unpack_codes
from core.snapshot import ViewSnapshot
from mapserver.merge.places import template_places

if TYPE_CHECKING:
    from core import Params
    from core.neocortex.descriptor import Match

#: front-end parameters that fix the shape and meaning of a cortex's cells: they must agree to merge
STRUCTURAL_KEYS: tuple[str, ...] = (
    "lsbh_bits", "lsbh_s", "lsbh_seed", "sp_columns", "sp_num_active_columns", "sp_potential_radius",
    "sp_potential_pct", "tm_cells_per_column", "sv_tm_topk", "sv_descriptor_source", "frontend_backbone",
    "template_x_size", "template_y_size",
)  # fmt: skip


def structural_difference(loaded: Params, partial: Params) -> str | None:
    """Return the first structural front-end parameter on which two ``sdr-htm`` maps differ (None: none)."""
    for key in STRUCTURAL_KEYS:
        a, b = getattr(loaded, key), getattr(partial, key)
        if a != b:
            return f"sdr-htm front-ends differ in {key}: {a!r} and {b!r}"
    return None


TEMPLATES, MEANS = ViewSnapshot.key("templates"), ViewSnapshot.key("means")  # the view cells' snapshot arrays
NULL_SAMPLE = 1024  # view cells (evenly spaced ids) whose codes estimate a map's look-alike overlaps
NULL_MIN_CELLS = 16  # fewer placed view cells than this: no estimate (the gate stays as given)


def null_overlap(codes: Float32Array, places: FloatArray, far_m: float, quantile: float) -> float:
    """Return the ``quantile`` of a map's look-alike overlaps: how well its views match places elsewhere in it.

    For each view cell i (up to :data:`NULL_SAMPLE`, evenly spaced ids, with a place), the best overlap
    recall R_ij = |c_i ∩ c_j| / |c_i| (Eq. 4.6 on the codes) over the view cells j placed more than ``far_m``
    metres from it: what a frame of place i would score against the wrong places of this very map. Their
    ``quantile`` (numpy's linear interpolation) is the overlap that the map's own imagery reaches by
    aliasing, so a gate below it accepts look-alikes as readily as the place itself; 0.0 when fewer than
    :data:`NULL_MIN_CELLS` cells have a place and a far partner. A calibration per map of the gate
    ``merge_sdr_min_overlap`` (measured: a street world's far views overlap 0.67–0.86 at the 99th percentile,
    a cave's 0.55–0.65; docs/journal.md, "a gate calibrated on the stored map's own look-alikes").
    """
    placed = np.flatnonzero(np.isfinite(places[:, 0]) & (codes.sum(axis=1) > 0))
    if placed.size > NULL_SAMPLE:
        placed = placed[np.linspace(0, placed.size - 1, NULL_SAMPLE).round().astype(np.int64)]
    if placed.size < NULL_MIN_CELLS:
        return 0.0
    sample, where = codes[placed], places[placed, :3]
    recall = (sample @ sample.T) / sample.sum(axis=1)[:, None]
    far = np.linalg.norm(where[:, None, :] - where[None, :, :], axis=2) > far_m
    best = np.where(far, recall, -1.0).max(axis=1)
    best = best[best >= 0.0]
    return float(np.quantile(best, quantile)) if best.size >= NULL_MIN_CELLS else 0.0


class CortexReader:
    """A stored ``sdr-htm`` map's place matcher (view cells' codes) and its cortex reading the session's frames.

    It answers the matcher calls of :class:`mapserver.merge.hypotheses.StoredPlaces` (``count``,
    ``match``, ``match_among``) for views that are the stacked readers' rows of one frame (:meth:`read`
    gives this reader's row: the descriptor, −1 padded to ``sv_tm_topk``, then the frame's packed SDR).

    Args:
        params: the session's parameters (its gates and threshold).
        state: the stored map's engine snapshot (prototypes, codes and cortex).
        row: this reader's row in the stacked views.
        key: the stored map's key.
        far_m: places further apart than this are different places to the gate's calibration.
        places: (N, 4) the view cells' places (:func:`mapserver.merge.places.template_places`), computed when None.
    """

    def __init__(
        self,
        params: Params,
        state: Mapping[str, np.ndarray],
        row: int,
        key: object = None,
        far_m: float = math.inf,
        places: FloatArray | None = None,
    ) -> None:
        gates = {"sv_min_intersection": min(params.merge_sv_min_intersection, params.sv_tm_topk),
                 "sv_enable_f1_gate": params.merge_sv_enable_f1_gate}  # fmt: skip
        self.cells = NeocortexViewCells.restore(params.replace(**gates), state)
        self.key = key
        self.row = row
        self.topk = params.sv_tm_topk
        self.limit = params.vt_match_threshold
        self.translations: dict[int, IntArray] = {}
        codes = unpack_codes(self.cells.codes, params.lsbh_bits)
        self.codes = codes.astype(np.float32) if codes.any() else None
        """(N, L) the view cells' codes as 0/1, or None: the map has none (made before ``lv_sdr``)."""
        self.min_overlap = params.merge_sdr_min_overlap
        """The gate R ≥ θ: ``merge_sdr_min_overlap``, raised to the map's own look-alikes (:func:`null_overlap`)."""
        if self.codes is not None and params.merge_sdr_null_quantile > 0.0:
            where = template_places(state)[0] if places is None else places
            null = null_overlap(self.codes, where, far_m, params.merge_sdr_null_quantile)
            self.min_overlap = max(self.min_overlap, null)
        self.miss_weight = params.miss_weight_reading(codes=self.codes is not None)
        self._recall_key = b""
        self._recall_of = np.zeros(0, dtype=np.float32)

    @property
    def count(self) -> int:
        """Return the number of the stored map's view cells."""
        return self.cells.count

    @property
    def width(self) -> int:
        """Return the length of this reader's row in a frame's views: ``sv_tm_topk`` + the packed SDR's bytes."""
        return self.topk + code_bytes(self.cells.params.lsbh_bits)

    def read(self, image: np.ndarray, sonar: np.ndarray | None = None, code: UInt8Array | None = None) -> IntArray:
        """Step the cortex on ``image`` (and ``sonar``; no learning); return its row: descriptor, then packed SDR.

        ``code``: the frame's packed SDR as the running session encoded it. The reader's encoder and projection
        are the session's (its parameters, and ``lsbh_*`` and the backbone are :data:`STRUCTURAL_KEYS`; the
        projection is regenerated from ``lsbh_seed`` and checked on restore), so the reader takes it instead of
        encoding the frame again (a second backbone pass per candidate map with ShuffleNetV2 or AlexNet).
        """
        d = self.cells.read(image, sonar, code)
        out = np.full(self.width, -1, dtype=np.int64)
        out[: d.size] = d
        assert self.cells.last_code is not None  # kept by read
        out[self.topk :] = self.cells.last_code
        return out

    def code_row(self, code: UInt8Array) -> IntArray:
        """Return a row that carries the frame's packed SDR ``code`` and no descriptor (−1): read by codes only."""
        out = np.full(self.width, -1, dtype=np.int64)
        out[self.topk :] = np.asarray(code, dtype=np.uint8)
        return out

    def remember(self, template: int, view: IntArray) -> None:
        """Keep this frame's descriptor as the map-cell prototype of the session's new view cell ``template``."""
        self.translations.setdefault(int(template), np.asarray(view)[self.row, : self.topk].astype(np.int64))

    def match(self, view: IntArray, mean: float, limit: float | None = None) -> tuple[int, float, float]:
        """Return (best accepted view cell or −1, an error ≤ ``limit`` when accepted else inf, 0.0) for a frame."""
        if self.codes is not None:
            return self._code_answer(view, None, limit)
        return self._answer(self.cells.match(self._descriptor(view)), limit)

    def match_among(
        self, view: IntArray, mean: float, ids: IntArray, limit: float | None = None
    ) -> tuple[int, float, float]:
        """Return :meth:`match`'s answer restricted to the view cells ``ids``."""
        ids = np.asarray(ids, dtype=np.int64)
        if ids.size == 0:
            return -1, math.inf, 0.0
        if self.codes is not None:
            return self._code_answer(view, np.unique(ids), limit)
        return self._answer(self.cells.match_among(self._descriptor(view), ids), limit)

    def _descriptor(self, view: IntArray) -> IntArray:
        row = np.asarray(view)[self.row, : self.topk].astype(np.int64)
        return row[row >= 0]

    def _code_answer(self, view: IntArray, ids: IntArray | None, limit: float | None) -> tuple[int, float, float]:
        """Return the best code match: R = |c ∩ c_ℓ| / |c| ≥ ``merge_sdr_min_overlap``; error ``limit·(1−R)/(1−θ)``."""
        every = self._recall(np.asarray(view)[self.row, self.topk :].astype(np.uint8))
        recall = every if ids is None else every[ids]
        if recall.size == 0:
            return -1, math.inf, 0.0
        best = int(np.argmax(recall))  # the first of equal overlaps: the lower id
        if recall[best] < self.min_overlap:
            return -1, math.inf, 0.0
        scale = self.limit if limit is None else limit
        index = best if ids is None else int(ids[best])
        return index, scale * (1.0 - float(recall[best])) / max(1.0 - self.min_overlap, 1e-9), 0.0

    def _recall(self, packed: UInt8Array) -> Float32Array:
        """Return R of a packed SDR against every view cell's code (the last frame's, kept: one product a frame)."""
        assert self.codes is not None
        key = packed.tobytes()
        if key != self._recall_key:
            code = unpack_codes(packed, self.codes.shape[1]).astype(np.float32)
            ones = float(code.sum())
            self._recall_key = key
            if ones and code.size == self.codes.shape[1]:
                self._recall_of = (self.codes @ code) / ones
            else:  # no SDR in the row (a track row of a session resumed from before lv_sdr): nothing matches
                self._recall_of = np.zeros(self.codes.shape[0], np.float32)
        return self._recall_of

    def _answer(self, found: Match | None, limit: float | None) -> tuple[int, float, float]:
        if found is None or not found.accepted:
            return -1, math.inf, 0.0
        scale = self.limit if limit is None else limit
        return found.index, scale * (1.0 - found.recall), 0.0

    def translated(self, partial: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Return the partial snapshot with its view cells as map-cell prototypes (``lv_templates``, ``lv_means``).

        A view cell without a remembered descriptor (made before a resume) gets an empty prototype.
        """
        n = int(np.shape(partial[MEANS])[0])
        rows = np.full((n, self.topk), -1, dtype=np.int64)
        for template, d in self.translations.items():
            if template < n:
                rows[template] = d
        sizes = (rows >= 0).sum(axis=1)
        return {**partial, TEMPLATES: rows.astype(np.float32)[:, None, :], MEANS: sizes.astype(np.float64)}

    def state(self) -> dict[str, np.ndarray]:
        """Return what the reader changed since it was restored: the sequence state and the translations."""
        ids = np.asarray(sorted(self.translations), dtype=np.int64)
        rows = np.asarray([self.translations[int(i)] for i in ids], dtype=np.int64).reshape(-1, self.topk)
        return {**self.cells.sequence_state(), "tr_ids": ids, "tr_rows": rows}

    def load(self, state: Mapping[str, np.ndarray]) -> None:
        """Continue from :meth:`state` arrays (a session resumed after ``--stop-after``)."""
        self.cells.load_sequence_state(state)
        rows = np.asarray(state["tr_rows"], dtype=np.int64).reshape(-1, self.topk)
        self.translations = {int(i): rows[n].copy() for n, i in enumerate(np.asarray(state["tr_ids"]))}

    def cortex(self) -> dict[str, np.ndarray]:
        """Return the reader's cortex as snapshot arrays (``nc_*``): the merged engine continues in it."""
        return {k: v for k, v in self.cells.snapshot().items() if k.startswith("nc_")}


def translate_offline(
    params: Params, loaded: Mapping[str, np.ndarray], partial: Mapping[str, np.ndarray]
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Return (the partial snapshot in the loaded map's cells, the cortex to continue in) for an offline merge.

    Online, the stored map's cortex reads the session's frames and each of the session's view cells gets the
    descriptor read at the frame that made it (:meth:`CortexReader.remember`). Offline there are no frames; what
    the partial map keeps of them is each view cell's code, the SDR of the frame that made it (``lv_sdr``), in
    creation order. The loaded map's cortex (learning off) reads those codes in that order and each view cell
    gets the descriptor read at its own code: the same sequence of inputs where the partial map made a view cell
    at every frame (``sdr-htm`` makes one nearly every frame), a sparser one where it recognised its own cells.
    """
    reader = CortexReader(params, loaded, row=0)
    codes = np.asarray(partial[ViewSnapshot.key("sdr")], dtype=np.uint8)
    for template in range(codes.shape[0]):
        reader.remember(template, reader.read(np.zeros(0), code=codes[template])[None, :])
    return reader.translated(partial), reader.cortex()


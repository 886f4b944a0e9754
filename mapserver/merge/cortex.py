"""Merge observations for maps of the ``sdr-htm`` front-end: the stored map's own cortex reads the session.

A view cell of the neocortical front-end (``core.neocortex``) is a set of its own temporal memory's
cells, and a spatial pooler that learnt on other frames maps the same image to other columns (measured
on ``cave3d``: after session 1, its pooler and session 2's agree on 35 % of the active columns for the
same image, median; matching session 2's descriptors against session 1's prototypes column by column
found no match at all). Two sessions' view cells are therefore not comparable. Each stored ``sdr-htm``
candidate map gets a **reader** instead: a copy of the map's cortex restored from its snapshot, stepped on
every frame of the running session with learning off (:meth:`NeocortexViewCells.read`), so it describes
the session's frames in the map's own cells (sequence context included); its descriptor is matched
against the map's prototypes (overlap recall R, I_min, τ_R, F1, IoU: PoseidonSLAM Eqs 4.6–4.9) with the
session's τ_R and the merge gates ``merge_sv_min_intersection`` (8) and ``merge_sv_enable_f1_gate`` (off):
at the thesis's gates (I_min 12 of 15, F1 ≥ 0.55) the reader recognised under 1.4 m of 23 m of shared
``cave3d`` ground on 3 of 4 seeds, too little to decide anything; a reading is only evidence here, weighed
by the sequential test with the front-end's own miss weight (``Params.miss_weight``: p₁ = 0.4, p₀ = 0.02).
An accepted match is an observation like an LVC template match (error reported as ``limit · (1 − R)``, so
"error ≤ threshold" means accepted; no heading offset), and the same hypotheses, evidence test and
probation decide and verify the merge (:mod:`mapserver.merge.online`).

Merging (Algorithm 1's operation (i) for SDR views): the partial map's view cells are re-expressed in the
map's cells: each gets the reader's descriptor at the frame that created it (:meth:`CortexReader.remember`);
the merged engine continues in the reader's cortex (the map's learnt state, the session's current
sequence state) and learns from then on, so the merged map has one cortex and every prototype in its cells.

Limits (stated in the README): a session joins at most one ``sdr-htm`` map (the first map's prototypes
were never read by a second map's cortex, so no bridge); maps merge only online, while the frames are
read (offline ``merge`` and ``--redo`` refuse them). A session stopped with ``--stop-after`` keeps its
readers' sequence state and translations with its merge driver's state (``MergerState.readers``), so it
resumes as one run; when a candidate map changed meanwhile, its readers and hypotheses restart instead.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from core.neocortex.viewcells import NeocortexViewCells

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


class CortexReader:
    """A stored ``sdr-htm`` map's cortex reading the session's frames; a place matcher over its prototypes.

    It answers the matcher calls of :class:`mapserver.merge.hypotheses.StoredPlaces` (``count``,
    ``match``, ``match_among``) for views that are the stacked readers' descriptors of one frame
    (:meth:`read` gives this reader's row, ``-1`` padded to ``sv_tm_topk``).

    Args:
        params: the session's parameters (its gates and threshold).
        state: the stored map's engine snapshot (prototypes and cortex).
        row: this reader's row in the stacked views.
    """

    def __init__(self, params: Params, state: Mapping[str, np.ndarray], row: int, key: object = None) -> None:
        gates = {"sv_min_intersection": min(params.merge_sv_min_intersection, params.sv_tm_topk),
                 "sv_enable_f1_gate": params.merge_sv_enable_f1_gate}  # fmt: skip
        self.cells = NeocortexViewCells.restore(params.replace(**gates), state)
        self.key = key
        self.row = row
        self.topk = params.sv_tm_topk
        self.limit = params.vt_match_threshold
        self.translations: dict[int, np.ndarray] = {}

    @property
    def count(self) -> int:
        """Return the number of the stored map's view cells."""
        return self.cells.count

    def read(self, image: np.ndarray, sonar: np.ndarray | None = None) -> np.ndarray:
        """Step the cortex on ``image`` (and ``sonar``; no learning); return its descriptor, −1 padded to top-k."""
        d = self.cells.read(image, sonar)
        out = np.full(self.topk, -1, dtype=np.int64)
        out[: d.size] = d
        return out

    def remember(self, template: int, view: np.ndarray) -> None:
        """Keep this frame's descriptor as the map-cell prototype of the session's new view cell ``template``."""
        self.translations.setdefault(int(template), np.asarray(view)[self.row].copy())

    def match(self, view: np.ndarray, mean: float, limit: float | None = None) -> tuple[int, float, float]:
        """Return (best accepted prototype or −1, ``limit·(1 − R)`` or inf, 0.0) for a frame's stacked views."""
        return self._answer(self.cells.match(self._descriptor(view)), limit)

    def match_among(
        self, view: np.ndarray, mean: float, ids: np.ndarray, limit: float | None = None
    ) -> tuple[int, float, float]:
        """Return :meth:`match`'s answer restricted to the prototypes ``ids``."""
        ids = np.asarray(ids, dtype=np.int64)
        if ids.size == 0:
            return -1, math.inf, 0.0
        return self._answer(self.cells.match_among(self._descriptor(view), ids), limit)

    def _descriptor(self, view: np.ndarray) -> np.ndarray:
        row = np.asarray(view)[self.row]
        return row[row >= 0]

    def _answer(self, found: Match | None, limit: float | None) -> tuple[int, float, float]:
        if found is None or not found.accepted:
            return -1, math.inf, 0.0
        scale = self.limit if limit is None else limit
        return found.index, scale * (1.0 - found.recall), 0.0

    def translated(self, partial: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Return the partial snapshot with its view cells as map-cell prototypes (``lv_templates``, ``lv_means``).

        A view cell without a remembered descriptor (made before a resume) gets an empty prototype.
        """
        n = int(np.shape(partial["lv_means"])[0])
        rows = np.full((n, self.topk), -1, dtype=np.int64)
        for template, d in self.translations.items():
            if template < n:
                rows[template] = d
        sizes = (rows >= 0).sum(axis=1)
        return {**partial, "lv_templates": rows.astype(np.float32)[:, None, :], "lv_means": sizes.astype(np.float64)}

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

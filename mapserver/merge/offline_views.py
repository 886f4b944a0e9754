"""The two maps' views as an offline merge reads them: map A's in creation order, map B's as a place matcher.

An offline merge (:mod:`mapserver.merge.offline`, :mod:`mapserver.merge.offline_evidence`) walks map A's views in
the order they were made (which follows A's trajectory), each with where A saw it, and asks map B which of its
views it matches and where B says that view is. What a view is depends on the front-end:

* ``lvc``: A's templates, each seen at its first experience; B's templates, matched by B's (or A's) local view
  cells (``LocalViewCells.match``), placed at their experiences.
* ``sdr-htm``: a view cell of one map is a set of that map's own temporal-memory cells, so two maps' prototypes
  are not comparable (:mod:`mapserver.merge.cortex`); their *codes* are: the LSBH SDR of the frame that made each
  view cell (``lv_sdr``, Eqs 4.1–4.3, a fixed seeded projection). A's view cells are its codes, each seen at its
  place (its experience plus the odometry since, :func:`mapserver.merge.places.template_places`); B's matcher is a
  :class:`~mapserver.merge.cortex.CortexReader` answering by overlap recall R = |c ∩ c_ℓ| / |c| ≥ the map's
  code gate (``merge_sdr_min_overlap``, raised to B's own look-alikes by ``merge_sdr_null_quantile``), the online
  merge's observation, and B predicts views at its experiences and at its view cells' places (loosely placed,
  as online: :class:`mapserver.merge.hypotheses.StoredPlaces`).

Both maps of an ``sdr-htm`` merge must hold codes (maps stored before ``lv_sdr`` existed do not): without them
nothing of A can be compared with B.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from core.arrays import FloatArray, IntArray, UInt8Array
from mapserver.merge.places import template_places
from mapserver.merge.snapshot import experiences_by_template

if TYPE_CHECKING:
    from core import Params
    from core.localview import LocalViewCells
    from mapserver.merge.cortex import CortexReader
    from mapserver.merge.engines import StoredMap


@dataclass(frozen=True)
class PartialViews:
    """Map A's views in creation order, and where A saw each (its own map frame and lattice)."""

    views: np.ndarray
    """(N, ...) each view as B's matcher takes it: a template, or a code row (no descriptor, the packed SDR)."""
    means: FloatArray
    """(N,) each view's mean intensity (0 for codes)."""
    poses: FloatArray
    """(N, 4) where A saw each view; rows of views seen nowhere are not used (``experiences`` −1)."""
    packets: FloatArray
    """(N, D) A's pose-cell packet there (its experience's)."""
    experiences: IntArray
    """(N,) the A experience each view is seen at (LVC) or placed after (``sdr-htm``); −1: none."""


@dataclass(frozen=True)
class StoredViews:
    """Map B as a predictor of views: its matcher, and the places it says each of its views is at."""

    matcher: LocalViewCells | CortexReader
    """``LocalViewCells`` or :class:`~mapserver.merge.cortex.CortexReader`: ``match``/``match_among``/``count``."""
    poses: FloatArray
    """(P, 4) B's places: its experiences, then (``sdr-htm``) its view cells' places."""
    templates: IntArray
    """(P,) the view of each place."""
    experiences: IntArray
    """(P,) the experience each place belongs to (an experience's own id, or a view cell's)."""
    order: IntArray
    """Places of view u are ``order[starts[u]:starts[u + 1]]``."""
    starts: IntArray
    loose: bool
    """Views are placed loosely (``sdr-htm``: :meth:`~mapserver.merge.hypotheses.StoredPlaces._placed_near`)."""

    @property
    def count(self) -> int:
        """Return the number of B's views."""
        return int(self.matcher.count)

    def places_of(self, view: int) -> IntArray:
        """Return the place indices of B's view ``view``."""
        return self.order[self.starts[view] : self.starts[view + 1]]


def uses_codes(stored: StoredMap) -> bool:
    """Return whether the map's views are ``sdr-htm`` view cells (matched offline by their codes)."""
    return stored.params.frontend == "sdr-htm"


def missing_codes(stored: StoredMap) -> str | None:
    """Return why an ``sdr-htm`` map cannot be compared offline (None: it can, or it has no view cells).

    Its view cells need codes and places; maps stored before ``lv_sdr``/``lv_place`` existed have neither.
    """
    codes = stored.snapshot.view.sdr
    n = int(np.shape(stored.snapshot.view.means)[0])
    if n and (codes is None or not np.asarray(codes).any()):
        return (
            f"map {stored.key!r} keeps no view-cell codes (lv_sdr: stored before they existed), so its sdr-htm view "
            "cells cannot be compared with another map's offline; merge it online (process a log into it)"
        )
    if n and not (template_places(stored.state)[1] >= 0).any():
        return (
            f"map {stored.key!r} keeps no view-cell places (lv_place: stored before they existed), so where its "
            "sdr-htm view cells were seen is unknown offline; merge it online (process a log into it)"
        )
    return None


def partial_views(partial: StoredMap) -> PartialViews:
    """Return map A's views (:class:`PartialViews`): templates at their first experience, or codes at their places."""
    state, view, em = partial.state, partial.snapshot.view, partial.snapshot.map
    n = int(np.shape(view.means)[0])
    em_pose = np.asarray(em.pose, dtype=np.float64).reshape(-1, 4)
    em_pc = np.asarray(em.pc, dtype=np.float64).reshape(em_pose.shape[0], -1)
    if uses_codes(partial):
        poses, experiences = template_places(state)
        views = code_rows(np.asarray(view.sdr, dtype=np.uint8), partial.params.sv_tm_topk)
        means = np.zeros(n)
    else:
        order, starts = experiences_by_template(np.asarray(em.template), n)
        first = np.append(order, -1)[starts[:-1]]  # each template's first experience (its lowest id)
        experiences = np.where(starts[1:] > starts[:-1], first, -1).astype(np.int64)
        poses = np.full((n, 4), np.nan)
        poses[experiences >= 0] = em_pose[experiences[experiences >= 0]]
        views = np.asarray(view.templates, dtype=np.float32)
        means = np.asarray(view.means, dtype=np.float64)
    packets = np.zeros((n, em_pc.shape[1]))
    packets[experiences >= 0] = em_pc[experiences[experiences >= 0]]
    return PartialViews(views, means, poses, packets, experiences)


def code_rows(codes: UInt8Array, topk: int) -> IntArray:
    """Return (N, 1, topk + bytes) rows that carry each packed code and no descriptor (−1): read by codes only."""
    rows = np.full((codes.shape[0], 1, topk + codes.shape[1]), -1, dtype=np.int64)
    rows[:, 0, topk:] = codes
    return rows


def stored_views(loaded: StoredMap, params: Params, far_m: float) -> StoredViews:
    """Return map B as a place matcher with the gates of ``params`` (:class:`StoredViews`).

    ``far_m``: places further apart than this are different places to the code gate's calibration
    (:func:`mapserver.merge.cortex.null_overlap`).
    """
    state = loaded.state
    poses = np.asarray(loaded.snapshot.map.pose, dtype=np.float64).reshape(-1, 4)
    templates = np.asarray(loaded.snapshot.map.template, dtype=np.int64).reshape(-1)
    experiences = np.arange(poses.shape[0], dtype=np.int64)
    n = int(np.shape(loaded.snapshot.view.means)[0])
    matcher: LocalViewCells | CortexReader
    if uses_codes(loaded):
        from mapserver.merge.cortex import CortexReader  # torch only for sdr-htm maps

        view_poses, view_anchor = template_places(state)
        placed = np.flatnonzero(view_anchor >= 0)
        poses = np.concatenate([poses, view_poses[placed]])
        templates = np.concatenate([templates, placed])
        experiences = np.concatenate([experiences, view_anchor[placed]])
        matcher = CortexReader(params, state, row=0, key=loaded.key, far_m=far_m, places=view_poses)
    else:
        from core.localview import LocalViewCells

        matcher = LocalViewCells.restore(params, state)
    order, starts = experiences_by_template(templates, n)
    return StoredViews(matcher, poses, templates, experiences, order, starts, loose=uses_codes(loaded))


def offline_incompatibility(loaded: StoredMap, partial: StoredMap) -> str | None:
    """Return why two stored maps cannot be merged offline (None: they can).

    As :func:`mapserver.merge.snapshot.params_incompatibility`; ``sdr-htm`` maps are compared by their codes,
    so they need the same cortex structure and both must keep codes (:func:`missing_codes`).
    """
    from mapserver.merge.snapshot import params_incompatibility

    codes = uses_codes(loaded) and uses_codes(partial)
    reason = params_incompatibility(loaded.params, partial.params, reads_frames=codes)
    if reason is None and codes:
        reason = missing_codes(partial) or missing_codes(loaded)
    return reason

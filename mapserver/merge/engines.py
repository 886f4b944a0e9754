"""Merging at the engine level: snapshot, ``merge_states``, restore, relax."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, cast

import numpy as np

from core import Engine, LinkKind
from core.arrays import Float32Array, IntArray
from core.snapshot import EngineSnapshot, ExperienceMapSnapshot, ViewSnapshot
from mapserver.errors import MergeError
from mapserver.merge.offline_views import offline_incompatibility
from mapserver.merge.places import merged_template_codes, merged_template_places
from mapserver.merge.record import Match, MergeRecord
from mapserver.merge.snapshot import params_incompatibility
from mapserver.merge.states import merge_states_apart, merged_templates

if TYPE_CHECKING:
    from core import Params
    from core.localview import LocalViewCells

#: The keys of the view cells' templates and their means in snapshot arrays.
TEMPLATES, MEANS = ViewSnapshot.key("templates"), ViewSnapshot.key("means")


@dataclass(frozen=True, eq=False)
class StoredMap:
    """A map of the atlas as the merge sees it: an opaque key, its parameters and its engine snapshot.

    Attributes:
        key: the store's id for the map (reported back in merge events).
        params: the parameters the map was built with.
        state: ``Engine.snapshot()`` arrays of the map.
    """

    key: object
    params: Params
    state: Mapping[str, np.ndarray]

    @cached_property
    def snapshot(self) -> EngineSnapshot:
        """Return :attr:`state` as typed parts (the same arrays)."""
        return EngineSnapshot.from_arrays(self.state)


def restore_merged(
    params: Params, state: Mapping[str, np.ndarray], record: MergeRecord, origin: int = 0
) -> Engine:
    """Return the engine of a merged snapshot with relaxation scheduled where the merge changed the graph.

    The snapshot is restored without its merge links (they are its last links) and with no
    pending relaxation; the merge links are then added with ``add_link_raw``, which puts
    their ends on the engine's relaxation worklist (and unanchors the joined part), so the
    engine's bounded per-frame relaxation starts where the two graphs meet instead of
    revisiting every experience. The result has the same arrays as the snapshot.
    """
    links = record.links
    tail = int(record.merge_links.size)
    if tail and not np.array_equal(record.merge_links, np.arange(links - tail, links)):
        msg = "merge links must be the last links of the merged snapshot"
        raise MergeError(msg)
    snapshot = EngineSnapshot.from_arrays(state)
    em, cut = snapshot.map, links - tail
    head = em.replace(
        link_from=np.asarray(em.link_from)[:cut], link_to=np.asarray(em.link_to)[:cut],
        link_transform=np.asarray(em.link_transform)[:cut], link_dt=np.asarray(em.link_dt)[:cut],
        link_distance=np.asarray(em.link_distance)[:cut], link_kind=np.asarray(em.link_kind)[:cut],
        relax_pending=np.asarray(False),
    )  # fmt: skip
    engine = Engine.restore(params, snapshot.replace(map=head).to_arrays(), origin=origin)
    active = em.link_status()
    for link in range(cut, links):
        engine.map.add_link_raw(
            int(em.link_from[link]),
            int(em.link_to[link]),
            np.asarray(em.link_transform[link], dtype=np.float64),
            float(em.link_dt[link]),
            float(em.link_distance[link]),
            LinkKind(int(em.link_kind[link])),
            active=bool(active[link]),
        )
    return engine


def _merged_state(
    loaded: Mapping[str, np.ndarray],
    partial: Mapping[str, np.ndarray],
    match: Match,
    shift_lattice: bool,
    identify_within: float | None,
    cortex: Mapping[str, np.ndarray] | None,
) -> tuple[dict[str, np.ndarray], MergeRecord, Float32Array]:
    """Return the merged snapshot less ``lv_templates``, its record, and the partial's kept templates.

    ``merge_states_apart`` and the view cells' places; the merged templates are the loaded map's followed by
    the kept ones (:func:`_restore_sharing`). ``cortex`` (``sdr-htm``): the ``nc_*`` arrays the merged map
    continues in; the view cells' codes are merged too.
    """
    state, record, appended = merge_states_apart(
        loaded, partial, match, shift_lattice=shift_lattice, identify_within=identify_within
    )
    state.update(merged_template_places(loaded, partial, record))
    if cortex is not None:
        state.update(cortex)
        state.update(merged_template_codes(loaded, partial, record))
    return state, record, appended


def _restore_sharing(
    params: Params,
    loaded: Mapping[str, np.ndarray],
    state: Mapping[str, np.ndarray],
    appended: Float32Array,
    record: MergeRecord,
    origin: int,
) -> Engine:
    """Return :func:`restore_merged` of a merged snapshot whose templates are ``loaded``'s followed by ``appended``.

    Intensity templates (``lvc``): the engine keeps the loaded map's float32 ``lv_templates`` array and then
    ``appended`` themselves, read-only (:meth:`core.localview.LocalViewCells.restore` and ``add_templates``
    share them), so the merge never copies the loaded map's templates; the engine equals the one restored from
    the joined snapshot. ``sdr-htm`` view cells restore from the joined snapshot.
    """
    if params.frontend == "sdr-htm":
        return restore_merged(params, {TEMPLATES: merged_templates(loaded, appended), **state}, record, origin)
    means = np.asarray(state[MEANS])
    n_loaded = means.shape[0] - appended.shape[0]
    head = {**state, TEMPLATES: loaded[TEMPLATES], MEANS: means[:n_loaded]}
    engine = restore_merged(params, head, record, origin=origin)
    cast("LocalViewCells", engine.local_view).add_templates(appended, means[n_loaded:], share=True)  # lvc here
    return engine


def stored_links(state: Mapping[str, np.ndarray]) -> int:
    """Return how many of a snapshot's first links a finished session left (``em_stored_links``; all when absent)."""
    em = ExperienceMapSnapshot.from_arrays(state)
    links = int(np.shape(em.link_from)[0])
    return min(int(em.stored_links if em.stored_links is not None else links), links)


def merge_engine(
    stored: StoredMap,
    engine: Engine,
    match: Match,
    *,
    shift_lattice: bool = True,
    identify_within: float | None = None,
    partial: Mapping[str, np.ndarray] | None = None,
    cortex: Mapping[str, np.ndarray] | None = None,
) -> tuple[Engine, MergeRecord]:
    """Merge a running engine (the partial map) into a stored map and return the engine to continue in.

    The merged engine keeps the running engine's parameters and origin tag; its loop-closure
    count carries over. Relaxation starts at the merge links (:func:`restore_merged`) and
    proceeds with the engine's per-frame relaxation; the partial's own pending relaxation
    work, if any, is not carried (its ids changed). Only the stored map's links count as a finished session's
    (``em_stored_links``, :func:`core.robust.switch_off_outliers`'s ``stored``): the running session's own links, kept
    by the merge, are still its own, unverified, until the session ends and its map settles (before 2026-11-30
    they counted as stored from the merge on). ``partial``: the engine's snapshot when
    the caller has taken it already (it is not taken again); for ``sdr-htm`` maps, with its view
    cells as the stored map's prototypes, and ``cortex`` the ``nc_*`` arrays the merged engine
    continues in (:mod:`mapserver.merge.cortex`).

    Raises:
        MergeError: the two maps cannot be merged (parameters or shapes differ, bad ids).
    """
    reason = params_incompatibility(stored.params, engine.params, reads_frames=cortex is not None)
    if reason:
        msg = f"cannot merge into map {stored.key!r}: {reason}"
        raise MergeError(msg)
    partial = engine.snapshot() if partial is None else partial
    state, record, appended = _merged_state(stored.state, partial, match, shift_lattice, identify_within, cortex)
    state[ExperienceMapSnapshot.key("stored_links")] = np.asarray(stored_links(stored.state), dtype=np.int64)
    merged = _restore_sharing(engine.params, stored.state, state, appended, record, engine.origin)
    merged.loop_closures = engine.loop_closures
    return merged, record


def merge_snapshots(
    loaded: StoredMap,
    partial: StoredMap,
    match: Match,
    *,
    shift_lattice: bool = True,
    identify_within: float | None = None,
    settle: bool = True,
    closures: Sequence[Sequence[int]] = (),
) -> tuple[Engine, MergeRecord]:
    """Merge stored map ``partial`` into stored map ``loaded`` (offline); return the merged engine and record.

    ``closures``: (partial experience, loaded experience) pairs that close a loop in the merged map
    (:func:`_close_loops`), before it settles.

    The merged map keeps ``loaded``'s parameters; ``sdr-htm`` maps continue in ``loaded``'s cortex, the
    partial's view cells re-expressed in its cells (:func:`mapserver.merge.cortex.translate_offline`). With
    ``settle`` the merged graph is moved to the fixed point of relaxation (``Engine.settle``), as a finished
    session's map is.

    Raises:
        MergeError: the two maps cannot be merged.
    """
    reason = offline_incompatibility(loaded, partial)
    if reason:
        msg = f"cannot merge map {partial.key!r} into {loaded.key!r}: {reason}"
        raise MergeError(msg)
    partial_state, cortex = partial.state, None
    if loaded.params.frontend == "sdr-htm":
        from mapserver.merge.cortex import translate_offline  # torch only for sdr-htm maps

        partial_state, cortex = translate_offline(loaded.params, loaded.state, partial.state)
    state, record, appended = _merged_state(loaded.state, partial_state, match, shift_lattice, identify_within, cortex)
    merged = _restore_sharing(loaded.params, loaded.state, state, appended, record, origin=0)
    _close_loops(merged, int(np.shape(loaded.snapshot.map.pose)[0]), record.experience_map, closures)
    if settle:
        merged.settle()
    return merged, record


def _close_loops(engine: Engine, n_loaded: int, experience_map: IntArray, closures: Sequence[Sequence[int]]) -> int:
    """Add a loop closure for every place where the partial map's views matched the loaded map's; return how many.

    An offline merge joins the partial map to the loaded one where it identified experiences (the
    confirmation window) and nowhere else, though the evidence walk found the partial's views matching the
    loaded map's along the whole overlap (:attr:`mapserver.merge.offline_evidence.OfflineEvidence.closures`):
    online, RatSLAM would have closed a loop at each of them. Each becomes a loop link from the loaded
    experience to the partial's (merged id ``experience_map[e]``) at the identity (the view says the robot
    stood there facing that way), unless the partial's experience was identified with a loaded one; the robust
    check decides them like any closure when the map settles.
    """
    added = 0
    for e, u in closures:
        merged = int(experience_map[e])
        if merged >= n_loaded and 0 <= u < n_loaded:
            added += engine.map.add_link_raw(u, merged, np.zeros(4), 0.0, 0.0, LinkKind.LOOP)
    return added

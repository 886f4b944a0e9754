"""Merges in the store: reading merge candidates, writing a merge with its provenance, offline merge.

The glue between :mod:`mapserver.merge` (pure merging of engine states) and :mod:`mapserver.store`
(rows, archives, merge events). ``pipeline.process_into_store`` writes the merges a session makes
online through :func:`write_merges`; ``mapserver merge`` calls :func:`merge_stored_maps`; undo and redo
(``mapserver unmerge``, ``mapserver merge --redo``) are :mod:`mapserver.atlas.undo`.

One merge event, in one write transaction (docs/architecture.md, "Merge", "Unmerge"): every stored
map involved is claimed at the version it was read (a concurrent writer → ``StaleMapError``, nothing
written); the event is recorded with its sessions, matches, lattice offset, SE(3) transform and
confirmations; the pre-merge state of every map involved is archived (stored maps from their rows,
the session's own partial map from memory); the joined maps are dropped and the merged state is
written into the *host*, the oldest map involved (lowest id), so a growing atlas keeps the name of
its first map. Undo restores the archives exactly; redo re-applies the recorded match to them.

Store-level snapshot keys written beside the engine's (kept generically by the store):

* ``st_next_index`` (S, 3) int64: per session, the next template and experience index of its stable
  identity (indices of rows a merge identified away are never given again);
* ``mg_*``: the online merge driver's state of a session stopped with ``--stop-after`` (resume):
  ``mg_session`` (), ``mg_map_version`` () (the map version it belongs to: a changed map voids the
  hypotheses), ``mg_odometry`` (4,), ``mg_absorbed`` (A,), ``mg_hypotheses``, ``mg_support``, ``mg_banned``,
  ``mg_track_*`` (:class:`mapserver.merge.resume.MergerState`), ``mg_versions`` (Q, 2) (candidate map id,
  version the hypotheses were built against).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from core import Params, params_from_dict
from mapserver.errors import InputError, MergeError
from mapserver.merge import Match, MergeRecord, StoredMap, merge_snapshots
from mapserver.merge.identity import RowIdentities, next_index_from_table
from mapserver.merge.offline_evidence import confirmed_offline_match
from mapserver.merge.provenance import match_to_dict, record_summary, transform7
from mapserver.merge.relevance import ViewLog
from mapserver.merge.snapshot import params_incompatibility
from mapserver.statuses import MergeStatus
from mapserver.store import Connection, Database, StaleMapError, UnknownMapError, claim_map, drop_map, get_map
from mapserver.store.archive import archive_map_state, archive_state
from mapserver.store.identities import index_maxima
from mapserver.store.maps import list_map_params, map_names
from mapserver.store.merge_events import (
    MergeEventSpec,
    record_merge_event,
)
from mapserver.store.sessions import get_sessions, sessions_of_map
from mapserver.store.state import WriteResult, read_map_state, read_map_templates, write_map_state

if TYPE_CHECKING:
    from mapserver.store import MapRecord

logger = logging.getLogger(__name__)

ID_NEXT_KEY = "st_next_index"


# ------------------------------------------------------------------------------------------------ reading


@dataclass(eq=False)
class AtlasMap:
    """A stored map as a merge sees it: its row, parameters, engine snapshot, identities and sessions."""

    id: int
    name: str
    version: int
    params: Params
    snapshot: dict[str, np.ndarray]
    identities: RowIdentities
    session_ids: list[int]
    partial_sessions: list[int]

    def stored(self) -> StoredMap:
        """Return the map as the merge algorithms take it (key = map id)."""
        return StoredMap(self.id, self.params, self.snapshot)


def stored_identities(
    conn: Connection, rows: Any, snapshot: Mapping[str, np.ndarray], session_ids: Sequence[int]
) -> RowIdentities:
    """Return stored rows' identities, next indices raised past every index their sessions ever used."""
    identities = RowIdentities.from_arrays(
        rows.template_session, rows.template_index, rows.experience_session, rows.experience_index,
        next_index_from_table(snapshot.get(ID_NEXT_KEY)),
    )  # fmt: skip
    for sid, (nt, ne) in index_maxima(conn=conn, session_ids=session_ids).items():
        identities.raise_next(sid, nt, ne)
    return identities


def read_atlas_map(conn: Connection, map_id: int) -> AtlasMap:
    """Load a stored map with its identities (next indices past every index its sessions ever used)."""
    content = read_map_state(conn=conn, map_id=map_id)
    meta = content.meta
    session_ids = [s.id for s in meta.sessions]
    identities = stored_identities(conn, meta, content.snapshot, session_ids)
    return AtlasMap(
        id=meta.map.id,
        name=meta.map.name,
        version=meta.map.version,
        params=params_from_dict(content.params),
        snapshot=content.snapshot,
        identities=identities,
        session_ids=session_ids,
        partial_sessions=[s.id for s in meta.sessions if not s.complete],
    )


def _eligible_maps(
    conn: Connection, *, params: Params, exclude: int | None, only: str | None = None
) -> tuple[dict[int, int], dict[str, str]]:
    """Return {map id: version} of the stored maps a session with ``params`` may merge into, and why not the others.

    ``only``: consider the map of that name alone (a session sent into one map).
    """
    rows = list_map_params(conn=conn)
    eligible: dict[int, int] = {}
    skipped: dict[str, str] = {}
    for map_id, name, map_params, version in rows:
        if (exclude is not None and int(map_id) == exclude) or (only is not None and name != only):
            continue
        try:
            reason = params_incompatibility(params_from_dict(dict(map_params)), params, reads_frames=True)
        except Exception as err:  # parameters stored by another version: not mergeable, say why
            reason = f"its parameters cannot be read ({err})"
        if reason is None:
            partial = [s.name for s in sessions_of_map(conn=conn, map_id=int(map_id)) if not s.complete]
            if partial:
                reason = f"session(s) {', '.join(map(repr, partial))} of it are still being processed (partial)"
        if reason:
            skipped[str(name)] = reason
            continue
        eligible[int(map_id)] = int(version)
    return eligible, skipped


def merge_candidates(
    conn: Connection, *, params: Params, exclude: int | None = None, only: str | None = None
) -> tuple[list[AtlasMap], dict[str, str]]:
    """Return the stored maps a session with ``params`` may merge into, and why the others may not.

    A map is a candidate when it is live (not archived), its parameters are compatible (lattice, template
    size, matcher geometry) and none of its sessions is still being processed (a partial session's robot
    state lives in its map; a merge would replace it). Maps are returned by id (oldest first). ``only``: the
    map of that name alone is considered (a session sent into one map).
    """
    eligible, skipped = _eligible_maps(conn, params=params, exclude=exclude, only=only)
    return [read_atlas_map(conn, map_id) for map_id in eligible], skipped


def merge_target_problem(conn: Connection, *, name: str, params: Params) -> str | None:
    """Return why the live map ``name`` cannot take a session with ``params`` (one line), None when it can."""
    _eligible, skipped = _eligible_maps(conn, params=params, exclude=None, only=name)
    return skipped.get(name)


def ensure_candidates_unchanged(
    conn: Connection,
    *,
    params: Params,
    exclude: int | None,
    seen: Mapping[int, int],
    relevance: tuple[set[object], ViewLog] | None = None,
    only: str | None = None,
) -> None:
    """Raise ``StaleMapError`` when the maps a session may merge into changed in a way that can matter to it.

    Call it in the session's write transaction after :func:`mapserver.store.lock_atlas`. A session is
    matched, frame by frame, against the candidates read when it started (``seen``: map id → version).
    If since then a map became a candidate (another session finished concurrently: its map is new, or
    its partial session completed) or a candidate changed, the session may connect to maps it never
    saw; the pipeline processes it again against the atlas as it is now, so sessions processed in
    parallel still merge with each other. With ``relevance`` (the session's observed map ids and its
    views, :mod:`mapserver.merge.relevance`), changes to maps it never observed and whose templates none
    of its views meets are let through: its run is what it would have been against the atlas as it is now.
    """
    now, _skipped = _eligible_maps(conn, params=params, exclude=exclude, only=only)
    if now == dict(seen):
        return
    differing = {k for k in now.keys() | seen.keys() if now.get(k) != seen.get(k)}
    if relevance is not None and not any(_matters(conn, k, k in now, params, *relevance) for k in sorted(differing)):
        logger.info("maps %s changed while the session ran; none of its views meets them: stored without a rerun",
                    sorted(differing))  # fmt: skip
        return
    names = map_names(conn=conn, map_ids=differing)
    changed = sorted(names.get(k, str(k)) for k in differing)
    msg = f"the maps this session may merge into changed while it was processed ({', '.join(map(repr, changed))})"
    raise StaleMapError(msg)


def _matters(
    conn: Connection, map_id: int, exists: bool, params: Params, observed: set[object], views: ViewLog
) -> bool:
    """Return whether a changed map can change the session's run: observed by it, or met by one of its views."""
    if map_id in observed:
        return True
    if not exists:  # it left the candidates: a map the session never observed cannot have steered it
        return False
    return views.any_match(read_map_templates(conn=conn, map_id=map_id), params)


# ------------------------------------------------------------------------------------------------ writing


@dataclass(eq=False)
class PartialSide:
    """The partial side of a merge as it was right before it (restored by an undo).

    Attributes:
        name: the map name it is restored under.
        map_id: its stored map, if it was one (an offline merge's map A; a resumed session's map).
        snapshot: engine snapshot; origins are tags (see ``tags`` in :func:`write_merges`).
        identities: its rows' identities (tags).
        params: its parameters.
        session_ids: its sessions (ids).
        from_store: archive it from its stored rows (it is ``map_id``'s state unchanged) instead of memory.
    """

    name: str
    map_id: int | None
    snapshot: Mapping[str, np.ndarray] | None
    identities: RowIdentities | None
    params: Params
    session_ids: list[int]
    from_store: bool = False


@dataclass(eq=False)
class MergeToWrite:
    """One merge event to store: the stored map merged into, the partial side, what was done.

    ``host_id``/``host_name``: the map that holds the merged result right after this event (the oldest
    map involved so far; an undo restores the maps named by its archives, this one among them).
    """

    mode: str
    target: AtlasMap
    partial: PartialSide
    match: Match
    record: MergeRecord
    host_id: int
    host_name: str
    details: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class WrittenMerges:
    """What :func:`write_merges` stored."""

    event_ids: list[int]
    host_id: int
    host_name: str
    result: WriteResult


def _retag(snapshot: Mapping[str, np.ndarray], tags: Mapping[int, int]) -> dict[str, np.ndarray]:
    out = dict(snapshot)
    for key in ("lv_origin", "em_origin"):
        values = np.asarray(snapshot[key], dtype=np.int64)
        mapped = values.copy()
        for tag, sid in tags.items():
            mapped[values == tag] = sid
        out[key] = mapped
    return out


def _uid(sessions: np.ndarray, indices: np.ndarray, row: int) -> list[int]:
    return [int(sessions[row]), int(indices[row])]


def _identified_rows(
    mapping: np.ndarray, offset: int, target: tuple[np.ndarray, np.ndarray], source: tuple[np.ndarray, np.ndarray]
) -> list[dict[str, Any]]:
    """Return the source rows a merge identified with target rows (``mapping[z] < offset``), with their uids."""
    return [
        {"target": int(mapping[z]), "source": int(z), "target_uid": _uid(*target, int(mapping[z])),
         "source_uid": _uid(*source, int(z))}
        for z in np.flatnonzero(mapping < offset).tolist()
    ]  # fmt: skip


def matches_json(target: AtlasMap, partial_ids: RowIdentities, record: MergeRecord) -> dict[str, Any]:
    """Return the event's ``matches``: identified template and experience pairs with stable identities."""
    templates = _identified_rows(np.asarray(record.template_map), record.template_offset,
                                 target.identities.template_arrays(), partial_ids.template_arrays())  # fmt: skip
    experiences = _identified_rows(np.asarray(record.experience_map), record.experience_offset,
                                   target.identities.experience_arrays(), partial_ids.experience_arrays())  # fmt: skip
    return {
        "anchor": {"target_template": record.stored_template, "target_experience": record.stored_experience,
                   "source_template": record.partial_template},
        "templates": templates,
        "experiences": experiences,
    }  # fmt: skip


def claim_all(conn: Connection, claimed: Mapping[int, int]) -> dict[int, int]:
    """Claim every map at the version it was read; return the new versions (a vanished map is stale)."""
    out: dict[int, int] = {}
    for map_id, version in sorted(claimed.items()):
        try:
            out[map_id] = claim_map(conn=conn, map_id=map_id, expected_version=version)
        except UnknownMapError as err:
            msg = f"a map this merge reads was dropped by another writer ({err}); nothing was written"
            raise StaleMapError(msg) from err
    return out


def write_merges(
    conn: Connection,
    *,
    merges: Sequence[MergeToWrite],
    claimed: Mapping[int, int],
    host_id: int,
    params: Params,
    snapshot: Mapping[str, np.ndarray],
    identities: RowIdentities,
    tags: Mapping[int, int],
    session_ids: Sequence[int],
    extra: Mapping[str, np.ndarray] | None = None,
) -> WrittenMerges:
    """Store merge events and the merged map in the caller's write transaction (see the module docstring).

    Args:
        conn: a connection in a write transaction.
        merges: the merge events, in the order they happened.
        claimed: every stored map involved → the version it was read at.
        host_id: the map (among ``claimed``) the merged state is written into; the others are dropped.
        params: the merged map's parameters.
        snapshot: the merged engine snapshot (origins are tags).
        identities: the merged rows' identities (tags).
        tags: origin tag → session id for tags that are not ids yet (a new session: ``{0: id}``).
        session_ids: the merged map's sessions.
        extra: more snapshot keys to store (``mg_*``).

    Raises:
        StaleMapError: a map changed or vanished since it was read (nothing is written).
    """
    versions = claim_all(conn, {k: v for k, v in claimed.items() if k != host_id})
    host = get_map_by_id_or_stale(conn, host_id)
    event_ids = [_record_applied_event(conn, merge, tags) for merge in merges]
    for map_id in sorted(versions):
        drop_map(conn=conn, map_id=map_id)
    state = {**dict(snapshot), ID_NEXT_KEY: identities.retagged(tags).next_table(), **dict(extra or {})}
    result = write_map_state(  # claims the host: a concurrent writer there → StaleMapError, nothing written
        conn=conn, map_id=host_id, expected_version=claimed[host_id], params=params, snapshot=state,
        session_ids=list(session_ids), origins={**{s: s for s in session_ids}, **dict(tags)},
        template_index=identities.template_arrays()[1], experience_index=identities.experience_arrays()[1],
    )  # fmt: skip
    for merge, event_id in zip(merges, event_ids, strict=True):
        _archive_partial_from_memory(conn, merge.partial, event_id, tags, host_id)
    return WrittenMerges(event_ids, host_id, host.name, result)


def _event_spec(
    merge: MergeToWrite, tags: Mapping[int, int], map_id: int, map_name: str, details: dict[str, Any], status: str
) -> MergeEventSpec:
    """Return the event row of a merge (transform, matches, sessions) recorded under map ``map_id``."""
    partial_ids = (merge.partial.identities or RowIdentities()).retagged(tags)
    return MergeEventSpec(
        map_id=map_id, map_name=map_name, mode=merge.mode, confirmations=merge.record.confirmations,
        lattice_offset=list(merge.record.lattice_offset), transform=transform7(merge.record),
        yaw=merge.record.transform[3], matches=matches_json(merge.target, partial_ids, merge.record),
        target_sessions=merge.target.session_ids, source_sessions=merge.partial.session_ids, details=details,
        status=status,
    )  # fmt: skip


def _record_applied_event(conn: Connection, merge: MergeToWrite, tags: Mapping[int, int]) -> int:
    """Record an applied merge's event, archive the stored maps it joins as they are; return the event id."""
    details = {**merge.details, "host": {"name": merge.host_name, "map_id": merge.host_id}}
    spec = _event_spec(merge, tags, merge.host_id, merge.host_name, details, MergeStatus.APPLIED)
    event_id = record_merge_event(conn=conn, spec=spec)
    archive_map_state(conn=conn, map_id=merge.target.id, event_id=event_id, role="target")
    if merge.partial.from_store and merge.partial.map_id is not None:
        archive_map_state(conn=conn, map_id=merge.partial.map_id, event_id=event_id, role="source")
    return event_id


def _archive_partial_from_memory(
    conn: Connection, side: PartialSide, event_id: int, tags: Mapping[int, int], host_id: int
) -> None:
    """Archive a merge's partial side from memory (a side read from the store was archived from its rows)."""
    if side.from_store or side.snapshot is None or side.identities is None:
        return
    ids = side.identities.retagged(tags)
    t_s, t_i = ids.template_arrays()
    e_s, e_i = ids.experience_arrays()
    archive_state(
        conn=conn, map_name=side.name, params=side.params,
        snapshot={**_retag(side.snapshot, tags), ID_NEXT_KEY: ids.next_table()},
        session_ids=side.session_ids, template_session=t_s, template_index=t_i, experience_session=e_s,
        experience_index=e_i, map_id=side.map_id if side.map_id == host_id else None,  # others are dropped
        event_id=event_id, role="source",
    )  # fmt: skip


def write_rejected_merges(conn: Connection, *, merges: Sequence[MergeToWrite], tags: Mapping[int, int]) -> list[int]:
    """Record online merges rolled back by their verification (status ``rejected``); return their event ids.

    No map changed (the session went on as its own map), so nothing is archived or claimed: the event
    keeps the transform, the matches and the evidence, under the stored map the session was wrongly
    merged into.
    """
    specs = [_event_spec(m, tags, m.target.id, m.target.name, dict(m.details), MergeStatus.REJECTED) for m in merges]
    return [record_merge_event(conn=conn, spec=spec) for spec in specs]


def get_map_by_id_or_stale(conn: Connection, map_id: int) -> MapRecord:
    """Return a map's row; a vanished map means another writer was first (``StaleMapError``)."""
    from mapserver.store.maps import get_map_by_id

    try:
        return get_map_by_id(conn=conn, map_id=map_id)
    except UnknownMapError as err:
        msg = f"map id {map_id} was dropped by another writer; nothing was written"
        raise StaleMapError(msg) from err


def merge_summary(event_id: int, merge: MergeToWrite, host_name: str) -> dict[str, Any]:
    """Return one entry of ``process --json``'s ``merges`` (see the README, "Multisession merging")."""
    r = merge.record
    x, y, z, yaw = r.transform
    return {
        "event": event_id,
        "into": merge.target.name,
        "map": host_name,
        "frame": merge.details.get("frame"),
        "stamp": merge.details.get("stamp"),
        "confirmations": r.confirmations,
        "matched_templates": int(np.count_nonzero(np.asarray(r.template_map) < r.template_offset)),
        "matched_experiences": int(np.count_nonzero(np.asarray(r.experience_map) < r.experience_offset)),
        "lattice_offset": [float(v) for v in r.lattice_offset],
        "lattice_shifted": r.lattice_shifted,
        "transform": {"x": x, "y": y, "z": z, "yaw": yaw},
        "status": merge.details.get("status", MergeStatus.APPLIED),
        "evidence": merge.details.get("evidence"),
    }


# ------------------------------------------------------------------------------------------------ offline


@dataclass(frozen=True)
class MergeOutcome:
    """What an offline merge or a redo did (``record``: None for a redo that restored the merged map's archive)."""

    event_id: int
    map_name: str
    record: MergeRecord | None
    sessions: list[str] = field(default_factory=list)
    settled: bool = True


IMPORTED_SOURCES = frozenset({"multisession-ratslam"})
"""Session sources whose poses another tool computed (``Session.source`` of an import)."""


def holds_imported_poses(conn: Connection, m: AtlasMap) -> bool:
    """Return whether a session of ``m`` was imported from another tool's save (its poses are that tool's)."""
    return any(s.source in IMPORTED_SOURCES for s in get_sessions(conn=conn, session_ids=list(m.session_ids)))


def merge_stored_maps(
    db: Database,
    *,
    source: str,
    into: str,
    confirm: int | None = None,
    evidence_m: float | None = None,
    settle: bool | None = None,
) -> MergeOutcome:
    """Merge stored map ``source`` (A) into stored map ``into`` (B) offline, with its event and archives.

    ``evidence_m``: metres of net agreement the alignment needs along A (None: A's ``merge_evidence_m``;
    0: the confirmed match alone, the paper's rule); see :func:`confirmed_offline_match`. ``settle``: move the
    merged graph to the fixed point of relaxation (with the robust check), as a finished session's map is; None
    settles unless a map holds poses imported from another tool's save (:func:`holds_imported_poses`), which
    then keep the poses they were saved with: the merge places A by its transform and adds its links.

    Raises:
        NotFoundError: a map does not exist.
        InputError: the same map twice, or ``confirm`` < 1.
        NoConfirmedMatchError: no confirmed template match, or its alignment not confirmed by the rest of A
            (:func:`mapserver.merge.offline_evidence.weigh_offline_match`; exit 2).
        MergeError: incompatible maps, or a map holds a session still being processed.
        StaleMapError: a map changed while merging (nothing written).
    """
    if source == into:
        msg = f"cannot merge map {source!r} into itself"
        raise InputError(msg)
    if confirm is not None and confirm < 1:
        msg = f"--confirm must be at least 1, got {confirm!r}"
        raise InputError(msg)
    if evidence_m is not None and not (evidence_m == -1 or evidence_m >= 0):
        msg = f"--merge-evidence must be -1 (the map's scale) or at least 0, got {evidence_m!r}"
        raise InputError(msg)
    with db.read() as conn:
        a = read_atlas_map(conn, get_map(conn=conn, name=source).id)
        b = read_atlas_map(conn, get_map(conn=conn, name=into).id)
    if settle is None:
        with db.read() as conn:
            settle = not (holds_imported_poses(conn, a) or holds_imported_poses(conn, b))
    for m in (a, b):
        if m.partial_sessions:
            msg = (
                f"map {m.name!r} holds a session still being processed (partial); finish it (process its log "
                "again) before merging"
            )
            raise MergeError(msg)
    stored_a, stored_b = StoredMap(a.name, a.params, a.snapshot), StoredMap(b.name, b.params, b.snapshot)
    match, evidence = confirmed_offline_match(stored_a, stored_b, confirm, evidence_m)
    closures = [list(pair) for pair in evidence.closures]
    engine, record = merge_snapshots(b.stored(), a.stored(), match, closures=closures, settle=settle)
    identities = RowIdentities.merged(b.identities, a.identities, record)
    host = a if a.id < b.id else b
    partial = PartialSide(a.name, a.id, None, a.identities, a.params, a.session_ids, from_store=True)
    merge = MergeToWrite(
        mode="offline", target=b, partial=partial, match=match, record=record, host_id=host.id, host_name=host.name,
        details={"match": match_to_dict(match), "record": record_summary(record), "settle": settle,
                 "source": {"name": a.name, "map_id": a.id}, "target": {"name": b.name, "map_id": b.id},
                 "session_frames": {}, "evidence": {"offline": evidence.as_dict()}, "closures": closures},
    )  # fmt: skip
    with db.write() as conn:
        sessions = sorted(set(a.session_ids) | set(b.session_ids))
        merge.details["session_frames"] = {
            str(s.id): s.frames_processed for s in get_sessions(conn=conn, session_ids=sessions)
        }
        written = write_merges(
            conn, merges=[merge], claimed={a.id: a.version, b.id: b.version}, host_id=host.id, params=b.params,
            snapshot=engine.snapshot(), identities=identities, tags={}, session_ids=sessions,
        )  # fmt: skip
    return MergeOutcome(written.event_ids[0], written.host_name, record, settled=settle)


__all__ = [
    "ID_NEXT_KEY",
    "AtlasMap",
    "MergeOutcome",
    "MergeToWrite",
    "PartialSide",
    "WrittenMerges",
    "claim_all",
    "matches_json",
    "merge_candidates",
    "merge_stored_maps",
    "merge_summary",
    "read_atlas_map",
    "stored_identities",
    "write_merges",
]

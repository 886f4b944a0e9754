"""Undo and redo of merge events (``mapserver unmerge``, ``mapserver merge --redo``) and moving a session out.

An unmerge, in one write transaction (docs/architecture.md, "Unmerge"): the merged map is archived as it is
(role ``merged``, with its sessions' progress rows), then every map the event joined is restored exactly as
the event's archives kept it. A redo restores that ``merged`` archive: the map the unmerge took apart, bit
for bit, frames processed after the merge included. An online merge's session leaves the unmerge with the
frames it had at the merge: complete there (a whole map of its own, mergeable), or, with ``rewind``, partial
(processing its log again continues it). :func:`move_session` is the unmerge of the event that brought a
session into its map, restoring the rest of the map under the map's name and the session under a new one.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from core import Engine, Params, params_from_dict
from mapserver.atlas import ID_NEXT_KEY, MergeOutcome, claim_all, stored_identities
from mapserver.errors import ConflictError, MergeError, NotFoundError
from mapserver.merge import Match, MergeRecord, StoredMap, merge_snapshots, merge_states, restore_merged
from mapserver.merge.identity import RowIdentities
from mapserver.merge.places import merged_template_places
from mapserver.merge.provenance import match_from_dict
from mapserver.merge.resume import MergerState, merger_keys
from mapserver.names import check_map_name, default_map_name, unique_map_name
from mapserver.statuses import MergeStatus
from mapserver.store import Connection, Database, drop_map, find_map, get_map_by_id
from mapserver.store.archive import (
    ArchivedState,
    ArchiveHead,
    archive_head,
    archive_map_state,
    delete_archive,
    load_archive,
    restore_map_states,
    restore_progress,
)
from mapserver.store.merge_events import (
    MERGED_ARCHIVE_ROLE,
    MergeEventRecord,
    get_merge_event,
    list_merge_events,
    set_merge_status,
    update_merge_details,
)
from mapserver.store.sessions import (
    cut_session,
    find_session_map,
    get_session_progress,
    get_sessions,
    sessions_of_map,
)
from mapserver.store.state import write_map_state

if TYPE_CHECKING:
    from mapserver.store.merge_events import MergeEventRecord


@dataclass(frozen=True)
class UnmergeOutcome:
    """What an unmerge restored.

    ``session_rewound``/``frames``: an online merge's session and the frames it keeps (those it had at the
    merge); ``session_status``: ``complete`` (its map ends there) or ``partial`` (``rewind``: continue it).
    """

    event_id: int
    maps: list[str]
    session_rewound: str | None = None
    frames: int | None = None
    session_status: str | None = None


@dataclass(frozen=True)
class MoveOutcome:
    """What moving a session out of its map did: the event undone, the session's new map and the rest's map."""

    session: str
    map: str
    rest: str
    event_id: int
    frames: int | None = None


def _event_sessions(event: MergeEventRecord) -> set[int]:
    return {int(s) for s in event.sessions}


def unmerge(db: Database, *, event_id: int, rewind: bool = False) -> UnmergeOutcome:
    """Undo a merge event: every map it joined is restored exactly as it was before it (one transaction).

    The merged map is archived first as it is (a redo gives it back, bit for bit). An online merge's
    session keeps the frames it had at the merge: complete there, its map whole and mergeable; with
    ``rewind`` partial, so that processing its log again continues it from the merge frame.

    Raises:
        NotFoundError: no such event.
        ConflictError: the event is not applied, a later applied event involves its sessions (undo that
            first), or a map it would restore holds a session that is none of its own.
    """
    with db.write() as conn:
        event = _undoable_event(conn, event_id)
        return _unmerge_in(conn, event, rewind=rewind, moved=None)


def _unmerge_in(
    conn: Connection, event: MergeEventRecord, *, rewind: bool, moved: tuple[int, str] | None
) -> UnmergeOutcome:
    """Undo ``event`` in the caller's write transaction; ``moved``: (archive id, name) restored under another name."""
    details = dict(event.details or {})
    archives = [archive_head(conn=conn, archive_id=a) for a in event.archive_ids]
    if not archives:
        msg = f"merge event {event.id} has no archived states to restore"
        raise ConflictError(msg)
    holder = _holding_map(conn, event)
    names = _restore_names(archives, str(details.get("host", {}).get("name", event.map_name)), holder.name, moved)
    _refuse_strangers(conn, event, {names.get(a.id, a.map_name) for a in archives} | {holder.name})
    progress = [get_session_progress(conn=conn, session_id=s) for s in sorted(_event_sessions(event))]
    archive_map_state(conn=conn, map_id=holder.id, event_id=event.id, role=MERGED_ARCHIVE_ROLE, progress=progress)
    if holder.name not in {names.get(a.id, a.map_name) for a in archives}:
        drop_map(conn=conn, map_id=holder.id)  # no archive takes its name back: its content is archived
    restored = restore_map_states(conn=conn, archive_ids=event.archive_ids, names=names)
    session, frames, status = _cut_online_session(conn, details, rewind)
    set_merge_status(conn=conn, event_id=event.id, status=MergeStatus.UNDONE)
    restored_names = [names.get(a.id, a.map_name) for a in archives]
    details["undo"] = {n: r.version for n, r in zip(restored_names, restored, strict=True)}
    details["undo_host"] = holder.name
    update_merge_details(conn=conn, event_id=event.id, details=details)
    return UnmergeOutcome(event.id, restored_names, session, frames, status)


def _holding_map(conn: Connection, event: MergeEventRecord) -> Any:
    """Return the map that holds the event's sessions now (the merged map)."""
    held = {s.map_id for s in get_sessions(conn=conn, session_ids=sorted(_event_sessions(event)))}
    if len(held) != 1 or None in held:
        msg = f"the sessions of merge event {event.id} are not in one map any more; it cannot be undone"
        raise ConflictError(msg)
    return get_map_by_id(conn=conn, map_id=int(next(iter(held))))  # type: ignore[arg-type]


def _restore_names(
    archives: Sequence[ArchiveHead], host_name: str, holder_name: str, moved: tuple[int, str] | None
) -> dict[int, str]:
    """Return archive id → name for archives restored under another name than their own.

    The archive of the map that hosted the merge takes the merged map's name now (it may have been renamed);
    a moved session's archive takes its new name, and then the other archive takes the merged map's name.
    """
    names: dict[int, str] = {}
    for a in archives:
        if moved is not None:
            names[a.id] = moved[1] if a.id == moved[0] else holder_name
        elif a.map_name == host_name and holder_name != host_name:
            names[a.id] = holder_name
    return names


def _undoable_event(conn: Connection, event_id: int) -> MergeEventRecord:
    """Return the merge event if it can be undone now: applied, and no later applied event shares its sessions."""
    event = get_merge_event(conn=conn, event_id=event_id)
    if event.status != MergeStatus.APPLIED:
        msg = f"merge event {event_id} is {event.status} already"
        raise ConflictError(msg)
    mine = _event_sessions(event)
    later = [e.id for e in list_merge_events(conn=conn) if e.id > event.id and e.status == MergeStatus.APPLIED
             and _event_sessions(e) & mine]  # fmt: skip
    if later:
        msg = (
            f"merge event {later[-1]} (later) involves the same sessions; undo it first "
            f"(merge events are undone newest first)"
        )
        raise ConflictError(msg)
    return event


def _refuse_strangers(conn: Connection, event: MergeEventRecord, names: set[str]) -> None:
    """Refuse (ConflictError) when a map the undo writes holds a session that is not one of the event's.

    Restoring the event's archives empties those maps: such a session would lose its map.
    """
    mine = _event_sessions(event)
    for name in sorted(names):
        record = find_map(conn=conn, name=name)
        if record is None:
            continue
        strangers = sorted(s.name for s in sessions_of_map(conn=conn, map_id=record.id) if s.id not in mine)
        if strangers:
            msg = (
                f"map {name!r} now holds session(s) {', '.join(map(repr, strangers))} that are not part of merge "
                f"event {event.id}; an unmerge would drop them"
            )
            raise ConflictError(msg)


def _cut_online_session(
    conn: Connection, details: Mapping[str, Any], rewind: bool
) -> tuple[str | None, int | None, str | None]:
    """Set an online merge's session back to the frames it had at the merge; return its name, frames and status.

    Complete there (its map, the event's archive of it, is whole), or partial with ``rewind``.
    """
    at, sid = details.get("frames_at"), details.get("session")
    if sid is None or at is None:
        return None, None, None
    pose = details.get("reckoning_pose")
    status = "partial" if rewind else "complete"
    session = cut_session(
        conn=conn, session_id=int(sid), frames=int(at), status=status, last_stamp=float(details["stamp"]),
        reckoning_pose=None if pose is None else (float(pose[0]), float(pose[1]), float(pose[2]), float(pose[3])),
    )  # fmt: skip
    return session.name, int(at), status


def move_session(db: Database, *, session: str, map_name: str | None = None) -> MoveOutcome:
    """Take a session out of its merged map into a new map of its own; the rest of the map stays whole.

    A merge identifies the session's views and places with the others' and, online, maps its later frames
    on theirs: its part cannot be cut out of the merged rows. It moves out by undoing the merge event that
    brought it in (the newest event of its map), when that leaves it alone on one side and the rest whole on
    the other: the rest is restored under the map's name, the session under ``map_name`` (default: its own
    name, made unique). An online merge's own session keeps the frames it had at the merge (complete).
    ``mapserver merge --redo`` puts the merged map back.

    Raises:
        NotFoundError: no such session.
        InputError: an invalid map name.
        ConflictError: the name is taken; the session is alone in its map, or in none; or entangled: it
            joined together with other sessions (an earlier merge), or another session was merged into it
            online (moving it out would cut that session back).
    """
    if map_name is not None:
        check_map_name(map_name)
    with db.write() as conn:
        sid, holder = _moved_session(conn, session)
        event = _event_that_brought_in(conn, sid, session, holder)
        archive = _archive_of(conn, event, sid, session)
        name = _free_map_name(conn, map_name, default_map_name(session))
        outcome = _unmerge_in(conn, event, rewind=False, moved=(archive, name))
    return MoveOutcome(session, name, holder.name, event.id, outcome.frames)


def _moved_session(conn: Connection, session: str) -> tuple[int, Any]:
    """Return the session's id and its map, refused when it is in none or alone in it."""
    found = find_session_map(conn=conn, name=session)
    if found is None:
        msg = f"no session named {session!r}"
        raise NotFoundError(msg)
    if found[1] is None:
        msg = f"session {session!r} belongs to no map"
        raise ConflictError(msg)
    holder = get_map_by_id(conn=conn, map_id=found[1])
    held = sessions_of_map(conn=conn, map_id=holder.id)
    if len(held) == 1:
        msg = f"session {session!r} is the only session of map {holder.name!r}; it has a map of its own already"
        raise ConflictError(msg)
    return next(s.id for s in held if s.name == session), holder


def _event_that_brought_in(conn: Connection, sid: int, session: str, holder: Any) -> MergeEventRecord:
    """Return the newest applied merge event of the session (refused when there is none or it cannot be undone)."""
    events = [e for e in list_merge_events(conn=conn) if e.status == MergeStatus.APPLIED and sid in e.sessions]
    if not events:
        msg = f"no applied merge event brought session {session!r} into map {holder.name!r}; it cannot be moved out"
        raise ConflictError(msg)
    return _undoable_event(conn, events[-1].id)


def _archive_of(conn: Connection, event: MergeEventRecord, sid: int, session: str) -> int:
    """Return the archive of the event that holds the session alone; refuse an entangled session, saying why."""
    details = event.details or {}
    online = details.get("session")
    if online is not None and int(online) != sid:
        other = get_sessions(conn=conn, session_ids=[int(online)])[0].name
        msg = (
            f"session {other!r} was merged into session {session!r}'s map online (merge event {event.id}) and mapped "
            f"on it since: moving {session!r} out would cut {other!r} back to its merge frame; `mapserver unmerge "
            f"--event {event.id}` separates them that way"
        )
        raise ConflictError(msg)
    for archive_id in event.archive_ids:
        held = archive_head(conn=conn, archive_id=archive_id).session_ids
        if sid in held:
            others = sorted(set(held) - {sid})
            if others:
                names = ", ".join(repr(s.name) for s in get_sessions(conn=conn, session_ids=others))
                msg = (
                    f"session {session!r} joined map {event.map_name!r} together with session(s) {names}, merged "
                    f"with it earlier: its places are merged with theirs; undo the merge events that joined them "
                    f"(`mapserver unmerge`, newest first) to separate them"
                )
                raise ConflictError(msg)
            return archive_id
    msg = f"merge event {event.id} kept no state of session {session!r}; it cannot be moved out"
    raise ConflictError(msg)


def _free_map_name(conn: Connection, wanted: str | None, default: str) -> str:
    """Return ``wanted`` when no map has it (else ConflictError), or ``default`` made unique with ``-2``, ``-3``."""
    if wanted is not None:
        if find_map(conn=conn, name=wanted) is not None:
            msg = f"a map named {wanted!r} already exists"
            raise ConflictError(msg)
        return wanted
    return unique_map_name(default, lambda name: find_map(conn=conn, name=name) is not None)


def redo_merge(db: Database, *, event_id: int) -> MergeOutcome:
    """Re-apply an undone merge event: the merged map its unmerge archived comes back exactly, bit for bit.

    That is the map as the unmerge found it: the same experiences, links, poses, engine state, identities
    and sessions' progress, frames processed after the merge included. An event undone before unmerges
    archived the merged map is re-applied from its recorded match on its archived states instead (an
    online merge's session then stays at the merge frame; processing its log again continues it).

    Raises:
        NotFoundError: no such event.
        ConflictError: the event is not undone, or its maps changed since the unmerge.
    """
    with db.write() as conn:
        event = get_merge_event(conn=conn, event_id=event_id)
        if event.status != MergeStatus.UNDONE:
            msg = f"merge event {event_id} is {event.status}; only an undone event can be redone"
            raise ConflictError(msg)
        if event.merged_archive is None:
            if event.mode == "manual":  # mapserver.atlas.manual_links.MANUAL_MODE: no view match to replay
                msg = (f"merge event {event_id} is a manual link undone without an archive of its map; add it "
                       "again to redo it (mapserver link, POST /v1/maps/{name}/links)")
                raise ConflictError(msg)
            return _redo_by_merging(conn, event)
        return _redo_from_archive(conn, event, event.merged_archive)


def _redo_from_archive(conn: Connection, event: MergeEventRecord, archive_id: int) -> MergeOutcome:
    """Restore the merged map an unmerge archived, in the map that held it; drop the other maps it restored."""
    details = dict(event.details or {})
    current = _maps_as_undone(conn, event.id, details.get("undo") or {})
    archived = load_archive(conn=conn, archive_id=archive_id)
    host_name = str(details.get("undo_host", archived.map_name))
    if host_name not in current:
        msg = f"merge event {event.id} does not say which map held it; it cannot be redone"
        raise ConflictError(msg)
    versions = claim_all(conn, {r.id: r.version for r in current.values()})  # a concurrent writer: stale
    for map_id in sorted(versions):
        if map_id != current[host_name].id:
            drop_map(conn=conn, map_id=map_id)
    (result,) = restore_map_states(conn=conn, archive_ids=[archive_id], names={archive_id: host_name})
    restore_progress(conn=conn, archived=archived)
    delete_archive(conn=conn, archive_id=archive_id)
    set_merge_status(conn=conn, event_id=event.id, status=MergeStatus.APPLIED)
    for key in ("undo", "undo_host"):
        details.pop(key, None)
    details["host"] = {**details.get("host", {}), "map_id": result.map_id}
    update_merge_details(conn=conn, event_id=event.id, details=details)
    names = [s.name for s in get_sessions(conn=conn, session_ids=list(archived.session_ids))]
    return MergeOutcome(event.id, host_name, None, names, settled=bool(details.get("settle", True)))


def _maps_as_undone(conn: Connection, event_id: int, undo: Mapping[str, Any]) -> dict[str, Any]:
    """Return the maps the undo restored (name → row); refused when one changed since."""
    current: dict[str, Any] = {}
    for name, version in undo.items():
        record = find_map(conn=conn, name=name)
        if record is None or record.version != int(version):
            msg = f"map {name!r} changed after merge event {event_id} was undone; it cannot be redone"
            raise ConflictError(msg)
        current[name] = record
    return current


def _redo_by_merging(conn: Connection, event: MergeEventRecord) -> MergeOutcome:
    """Re-apply an event undone without a ``merged`` archive: its recorded match on its archived states."""
    event_id = event.id
    details = dict(event.details or {})
    current, target, source = _restored_maps_and_archives(conn, event_id, details.get("undo") or {}, event)
    match = match_from_dict(details["match"])
    shift = bool((details.get("record") or {}).get("lattice_shifted", True))
    t_params, s_params = params_from_dict(target.params), params_from_dict(source.params)
    t_ids = stored_identities(conn, target, target.snapshot, target.session_ids)
    s_ids = stored_identities(conn, source, source.snapshot, source.session_ids)
    settle = bool(details.get("settle", True))
    extra: dict[str, np.ndarray]
    if event.mode == "offline":
        engine, record = merge_snapshots(
            StoredMap(target.map_name, t_params, target.snapshot),
            StoredMap(source.map_name, s_params, source.snapshot), match, shift_lattice=shift,
            closures=details.get("closures") or (), settle=settle,
        )  # fmt: skip
        params, extra = t_params, {}
    else:
        engine, record, extra = _redo_online(conn, details, target, source, match, shift, s_params, current)
        params = s_params
    identities = RowIdentities.merged(t_ids, s_ids, record)
    host_name = details["host"]["name"]
    host = current[host_name]
    versions = claim_all(conn, {r.id: r.version for r in current.values() if r.id != host.id})
    for map_id in sorted(versions):
        drop_map(conn=conn, map_id=map_id)
    sessions = sorted(set(target.session_ids) | set(source.session_ids))
    state_out = {**engine.snapshot(), ID_NEXT_KEY: identities.next_table(), **extra}
    result = write_map_state(
        conn=conn, map_id=host.id, expected_version=host.version, params=params, snapshot=state_out,
        session_ids=sessions, template_index=identities.template_arrays()[1],
        experience_index=identities.experience_arrays()[1],
    )  # fmt: skip
    set_merge_status(conn=conn, event_id=event_id, status=MergeStatus.APPLIED)
    details.pop("undo", None)
    details["host"] = {**details["host"], "map_id": result.map_id}
    update_merge_details(conn=conn, event_id=event_id, details=details)
    names = [s.name for s in get_sessions(conn=conn, session_ids=sessions)]
    return MergeOutcome(event_id, host_name, record, names, settled=settle)


def _restored_maps_and_archives(
    conn: Connection, event_id: int, undo: Mapping[str, Any], event: Any
) -> tuple[dict[str, Any], ArchivedState, ArchivedState]:
    """Return the maps the undo restored (name → row; refused if changed since) and the event's two archives."""
    current = _maps_as_undone(conn, event_id, undo)
    archives = [load_archive(conn=conn, archive_id=a) for a in event.archive_ids]
    targets = [a for a in archives if a.role == "target"]
    sources = [a for a in archives if a.role == "source"]
    if len(targets) != 1 or len(sources) != 1:
        msg = f"merge event {event_id} does not have one target and one source archive"
        raise ConflictError(msg)
    return current, targets[0], sources[0]


def _redo_online(
    conn: Connection, details: Mapping[str, Any], target: ArchivedState, source: ArchivedState, match: Match,
    shift: bool, s_params: Params, current: Mapping[str, Any],
) -> tuple[Engine, MergeRecord, dict[str, np.ndarray]]:  # fmt: skip
    """Return an online merge re-applied: the merged engine, its record and the merge driver's snapshot keys."""
    if s_params.frontend == "sdr-htm":
        msg = ("an online merge of sdr-htm maps cannot be redone: its view cells were read by the stored "
               "map's cortex from the session's frames (unmerge keeps both maps; process the log again)")
        raise MergeError(msg)
    state, record = merge_states(target.snapshot, source.snapshot, match, shift_lattice=shift)
    state.update(merged_template_places(target.snapshot, source.snapshot, record))
    sid = int(details["session"])
    engine = restore_merged(s_params, state, record, origin=sid)
    engine.loop_closures = int(source.snapshot.get("eng_loop_closures", np.asarray(0)))
    extra: dict[str, np.ndarray] = {}
    session = get_sessions(conn=conn, session_ids=[sid])[0]
    if not session.complete:
        state_after = MergerState(np.asarray(details.get("odometry", [0.0] * 4), dtype=np.float64))
        version_after = current[details["host"]["name"]].version + 1
        extra = merger_keys(state_after, session_id=sid, map_version=version_after, candidates=[])
    return engine, record, extra


__all__ = ["MoveOutcome", "UnmergeOutcome", "move_session", "redo_merge", "unmerge"]

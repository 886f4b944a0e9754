"""Undo and redo of merge events: ``mapserver unmerge`` and ``mapserver merge --redo``.

An unmerge restores, in one write transaction, every map a merge event involved exactly as the event's
archives kept it (docs/architecture.md, "Unmerge"); a redo re-applies the event's recorded match to those
archives and writes the result as the original merge was (:mod:`mapserver.atlas` writes merges).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from core import Engine, Params, params_from_dict
from mapserver.atlas import ID_NEXT_KEY, MergeOutcome, claim_all, stored_identities
from mapserver.errors import ConflictError, MergeError
from mapserver.merge import Match, MergeRecord, StoredMap, merge_snapshots, merge_states, restore_merged
from mapserver.merge.identity import RowIdentities
from mapserver.merge.places import merged_template_places
from mapserver.merge.provenance import match_from_dict
from mapserver.merge.resume import MergerState, merger_keys
from mapserver.store import Connection, Database, drop_map, find_map
from mapserver.store.archive import ArchivedState, load_archive, restore_map_states
from mapserver.store.merge_events import get_merge_event, list_merge_events, set_merge_status, update_merge_details
from mapserver.store.sessions import get_reckoning, get_sessions, sessions_of_map, update_session
from mapserver.store.state import write_map_state

if TYPE_CHECKING:
    from mapserver.store.merge_events import MergeEventRecord


@dataclass(frozen=True)
class UnmergeOutcome:
    """What an unmerge restored."""

    event_id: int
    maps: list[str]
    session_rewound: str | None = None
    frames: int | None = None


def _event_sessions(event: MergeEventRecord) -> set[int]:
    return {int(s) for s in event.sessions}


def unmerge(db: Database, *, event_id: int) -> UnmergeOutcome:
    """Undo a merge event: every map involved is restored exactly as it was before it (one transaction).

    A session whose frames after the merge lived in the merged map (an online merge) is set back to
    the merge frame: processing its log again continues it from there (with or without merging).

    Raises:
        NotFoundError: no such event.
        ConflictError: the event is not applied, a later applied event involves its sessions (undo that
            first), or the maps changed after it in a way an undo would lose (a session processed further,
            another session joined, a map of the same name created).
    """
    with db.write() as conn:
        event = _undoable_event(conn, event_id)
        details = dict(event.details or {})
        archives = [load_archive(conn=conn, archive_id=a) for a in event.archive_ids]
        if not archives:
            msg = f"merge event {event_id} has no archived states to restore"
            raise ConflictError(msg)
        frames = {int(k): int(v) for k, v in (details.get("session_frames") or {}).items()}
        _refuse_if_maps_moved_on(conn, event, {a.map_name for a in archives}, frames)
        restored = restore_map_states(conn=conn, archive_ids=event.archive_ids)
        rewound = _rewind_session(conn, details)
        set_merge_status(conn=conn, event_id=event_id, status="undone")
        details["undo"] = {a.map_name: r.version for a, r in zip(archives, restored, strict=True)}
        update_merge_details(conn=conn, event_id=event_id, details=details)
    at = details.get("frames_at")
    return UnmergeOutcome(event_id, [a.map_name for a in archives], rewound, None if at is None else int(at))


def _undoable_event(conn: Connection, event_id: int) -> MergeEventRecord:
    """Return the merge event if it can be undone now: applied, and no later applied event shares its sessions."""
    event = get_merge_event(conn=conn, event_id=event_id)
    if event.status != "applied":
        msg = f"merge event {event_id} is {event.status} already"
        raise ConflictError(msg)
    mine = _event_sessions(event)
    later = [e.id for e in list_merge_events(conn=conn) if e.id > event.id and e.status == "applied"
             and _event_sessions(e) & mine]  # fmt: skip
    if later:
        msg = (
            f"merge event {later[-1]} (later) involves the same sessions; undo it first "
            f"(merge events are undone newest first)"
        )
        raise ConflictError(msg)
    return event


def _refuse_if_maps_moved_on(
    conn: Connection, event: MergeEventRecord, names: set[str], frames: Mapping[int, int]
) -> None:
    """Refuse (ConflictError) when restoring the event's archives would lose work done since.

    That is, a map it involved holds a session that joined after it, or a session processed past its frame
    count at the merge (``frames``).
    """
    mine = _event_sessions(event)
    for name in sorted(names | {event.map_name}):
        record = find_map(conn=conn, name=name)
        if record is None:
            continue
        held = {s.id: s for s in sessions_of_map(conn=conn, map_id=record.id)}
        strangers = sorted(s.name for sid, s in held.items() if sid not in mine)
        if strangers:
            msg = (
                f"map {name!r} now holds session(s) {', '.join(map(repr, strangers))} that joined after merge "
                f"event {event.id}; an unmerge would drop them"
            )
            raise ConflictError(msg)
        ahead = sorted(s.name for sid, s in held.items() if sid in frames and s.frames_processed > frames[sid])
        if ahead:
            msg = (
                f"session(s) {', '.join(map(repr, ahead))} of map {name!r} were processed further after merge "
                f"event {event.id}; an unmerge would lose those frames"
            )
            raise ConflictError(msg)


def _rewind_session(conn: Connection, details: Mapping[str, Any]) -> str | None:
    """Set an online merge's session back to the merge frame (partial, its dead reckoning cut there); its name."""
    at = details.get("frames_at")
    sid = details.get("session")
    if sid is None or at is None:
        return None
    session = get_sessions(conn=conn, session_ids=[int(sid)])[0]
    rows, _pose = get_reckoning(conn=conn, session_id=session.id)
    pose = details.get("reckoning_pose")
    update_session(
        conn=conn, session_id=session.id, status="partial", frames_processed=int(at),
        last_stamp=float(details["stamp"]), reckoning=rows[: int(at)],
        reckoning_pose=None if pose is None else tuple(float(v) for v in pose),  # type: ignore[arg-type]
    )  # fmt: skip
    return session.name


def redo_merge(db: Database, *, event_id: int) -> MergeOutcome:
    """Re-apply an undone merge event: its recorded match on its archived states, written as the original was.

    The result equals the original merge bit for bit (``merge_states`` is deterministic). For an online
    merge the session stays at the merge frame; processing its log again continues it in the merged map
    exactly as the original run did.

    Raises:
        NotFoundError: no such event.
        ConflictError: the event is not undone, or its maps changed since the unmerge.
    """
    with db.write() as conn:
        event = get_merge_event(conn=conn, event_id=event_id)
        if event.status != "undone":
            msg = f"merge event {event_id} is {event.status}; only an undone event can be redone"
            raise ConflictError(msg)
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
        set_merge_status(conn=conn, event_id=event_id, status="applied")
        details.pop("undo", None)
        details["host"] = {**details["host"], "map_id": result.map_id}
        update_merge_details(conn=conn, event_id=event_id, details=details)
        names = [s.name for s in get_sessions(conn=conn, session_ids=sessions)]
    return MergeOutcome(event_id, host_name, record, names, settled=settle)


def _restored_maps_and_archives(
    conn: Connection, event_id: int, undo: Mapping[str, Any], event: MergeEventRecord
) -> tuple[dict[str, Any], ArchivedState, ArchivedState]:
    """Return the maps the undo restored (name → row; refused if changed since) and the event's two archives."""
    current: dict[str, Any] = {}
    for name, version in undo.items():
        record = find_map(conn=conn, name=name)
        if record is None or record.version != int(version):
            msg = f"map {name!r} changed after merge event {event_id} was undone; it cannot be redone"
            raise ConflictError(msg)
        current[name] = record
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


__all__ = ["UnmergeOutcome", "redo_merge", "unmerge"]

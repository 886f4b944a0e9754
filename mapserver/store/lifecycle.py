"""A map's lifecycle: delete (archive), restore, rename, purge.

Deleting a map archives it: ``maps.archived_at`` is set and nothing else changes — its content (templates,
pose-cell links, experiences, links, state), its sessions, their evidence and logs' identities, and the merge
events that built it all stay as they are. An archived map is hidden: lookups by name answer "no map"
(:func:`mapserver.store.maps.find_map`), listings leave it out unless asked for archived maps, it is no merge
candidate, and its sessions are not processed further until it is restored. Its name stays held (a new map
cannot take it) until it is restored (the same map, bit for bit: nothing was rewritten) or purged.

Purging deletes an archived map for good: its content, its sessions (with their templates and evidence) and
every merge event that produced it or involved one of its sessions (with their archived states). Jobs keep
their history with the session and map left empty. The name and the logs are free again afterwards.

Renaming changes the map's name, and the name its merge events, their details and archived states record (an
unmerge restores the map under its current name, a redo finds it by it). A new name follows
:func:`mapserver.names.check_map_name`.

Each function runs inside the caller's write transaction; archive and restore take the atlas lock
(:func:`mapserver.store.maps.lock_atlas`) so that a session being stored sees the maps it may merge into
either before or after the change, never half of it.
"""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import Connection, delete, select, update

from mapserver.errors import ConflictError
from mapserver.names import check_map_name
from mapserver.store.admission import PENDING, lock_admission, pending_map_creator
from mapserver.store.errors import MapExistsError, UnknownMapError
from mapserver.store.maps import MapRecord, clear_map, find_map, lock_atlas
from mapserver.store.models import (
    Evidence,
    Job,
    Map,
    MapArchive,
    MergeEvent,
    MergeEventSession,
    Session,
    Template,
    utcnow,
)


@dataclass(frozen=True, slots=True)
class PurgeOutcome:
    """What purging a map deleted: its name, and how many sessions and merge events went with it."""

    name: str
    sessions: int
    merge_events: int

    def as_dict(self) -> dict[str, object]:
        """Return ``{"purged": name, "sessions", "merge_events"}``."""
        return {"purged": self.name, "sessions": self.sessions, "merge_events": self.merge_events}


def _live(conn: Connection, name: str, doing: str) -> MapRecord:
    """Return the live map ``name``; 409 when it is archived, 404 when there is none."""
    record = find_map(conn=conn, name=name, archived=None)
    if record is None:
        msg = f"no map named {name!r} in this database"
        raise UnknownMapError(msg)
    if record.archived_at is not None:
        msg = f"map {name!r} is archived (deleted); restore it before you {doing} it"
        raise ConflictError(msg)
    return record


def _archived(conn: Connection, name: str, doing: str) -> MapRecord:
    """Return the archived map ``name``; 409 when it is live, 404 when there is none."""
    record = find_map(conn=conn, name=name, archived=None)
    if record is None:
        msg = f"no map named {name!r} in this database"
        raise UnknownMapError(msg)
    if record.archived_at is None:
        msg = f"map {name!r} is not archived; delete it first, then {doing} it"
        raise ConflictError(msg)
    return record


def _refuse_if_busy(conn: Connection, name: str, doing: str) -> None:
    """Refuse (409) while a queued or running job processes into the map ``name``."""
    job = conn.execute(
        select(Job.id).where(Job.map_name == name, Job.status.in_(PENDING)).order_by(Job.id).limit(1)
    ).scalar_one_or_none()
    if job is not None:
        msg = f"job {int(job)} is processing a log into map {name!r}; {doing} it when that job has ended"
        raise ConflictError(msg)


def archive_map(*, conn: Connection, name: str) -> MapRecord:
    """Delete a map by archiving it (restorable); return it as it is now.

    Raises:
        UnknownMapError: no map of that name.
        ConflictError: the map is archived already, or a pending job processes a log into it.
    """
    lock_atlas(conn=conn)
    record = find_map(conn=conn, name=name, archived=None)
    if record is not None and record.archived_at is not None:
        msg = f"map {name!r} is archived already; restore it, or purge it for good"
        raise ConflictError(msg)
    record = _live(conn, name, "delete")
    _refuse_if_busy(conn, name, "delete")
    now = utcnow()
    conn.execute(update(Map).where(Map.id == record.id).values(archived_at=now))
    return MapRecord(record.id, record.name, record.version, record.params, record.created_at, record.updated_at, now)


def restore_map(*, conn: Connection, name: str) -> MapRecord:
    """Bring an archived map back as it was when it was deleted; return it.

    Raises:
        UnknownMapError: no map of that name.
        ConflictError: the map is not archived.
    """
    lock_atlas(conn=conn)
    record = _archived(conn, name, "restore")
    conn.execute(update(Map).where(Map.id == record.id).values(archived_at=None))
    return MapRecord(record.id, record.name, record.version, record.params, record.created_at, record.updated_at)


def rename_map(*, conn: Connection, name: str, new_name: str) -> MapRecord:
    """Give a live map a new name (also in its merge events and archived states); return it.

    Raises:
        InputError: the new name breaks the map name rule.
        UnknownMapError: no map called ``name``.
        MapExistsError: a live or archived map holds the new name.
        ConflictError: the map is archived; a pending job processes into it, or creates a map of the new name.
    """
    check_map_name(new_name)
    lock_admission(conn=conn)  # a concurrent upload's admission sees the names before or after
    record = _live(conn, name, "rename")
    if new_name == name:
        return record
    holder = find_map(conn=conn, name=new_name, archived=None)
    if holder is not None:
        state = "an archived (deleted) map" if holder.archived_at is not None else "another map"
        msg = f"the name {new_name!r} is held by {state}; choose another name"
        raise MapExistsError(msg)
    _refuse_if_busy(conn, name, "rename")
    creator = pending_map_creator(conn=conn, name=new_name)
    if creator is not None:
        msg = f"job {creator} is creating a map named {new_name!r}; choose another name"
        raise ConflictError(msg)
    conn.execute(update(Map).where(Map.id == record.id).values(name=new_name))
    conn.execute(update(MergeEvent).where(MergeEvent.map_id == record.id).values(map_name=new_name))
    conn.execute(update(MapArchive).where(MapArchive.map_id == record.id).values(map_name=new_name))
    _rename_in_details(conn, record.id, name, new_name)
    return MapRecord(record.id, new_name, record.version, record.params, record.created_at, record.updated_at)


def _rename_in_details(conn: Connection, map_id: int, name: str, new_name: str) -> None:
    """Rename the map where its merge events' details name it: an online merge's host, the maps an undo restored.

    A redo finds the maps by these names (:mod:`mapserver.atlas.undo`).
    """
    rows = conn.execute(select(MergeEvent.id, MergeEvent.details).where(MergeEvent.map_id == map_id)).all()
    for event_id, details in rows:
        if not details:
            continue
        changed = dict(details)
        host = changed.get("host")
        if isinstance(host, dict) and host.get("map_id") == map_id and host.get("name") == name:
            changed["host"] = {**host, "name": new_name}
        undo = changed.get("undo")
        if isinstance(undo, dict) and name in undo:
            changed["undo"] = {new_name if k == name else k: v for k, v in undo.items()}
        if changed.get("undo_host") == name:  # the map that held the merge when it was undone
            changed["undo_host"] = new_name
        if changed != details:
            conn.execute(update(MergeEvent).where(MergeEvent.id == event_id).values(details=changed))


def purge_map(*, conn: Connection, name: str) -> PurgeOutcome:
    """Delete an archived map for good, with its sessions and the merge events that involve it.

    Raises:
        UnknownMapError: no map of that name.
        ConflictError: the map is live (delete it first: purging takes an archived map only).
    """
    lock_atlas(conn=conn)
    record = _archived(conn, name, "purge")
    sessions = [int(s) for s in conn.execute(select(Session.id).where(Session.map_id == record.id)).scalars()]
    events = set(conn.execute(select(MergeEvent.id).where(MergeEvent.map_id == record.id)).scalars())
    if sessions:
        involved = select(MergeEventSession.event_id).where(MergeEventSession.session_id.in_(sessions))
        events |= set(conn.execute(involved).scalars())
    event_ids = sorted(int(e) for e in events)
    if event_ids:
        conn.execute(delete(MapArchive).where(MapArchive.event_id.in_(event_ids)))
        conn.execute(delete(MergeEventSession).where(MergeEventSession.event_id.in_(event_ids)))
        conn.execute(delete(MergeEvent).where(MergeEvent.id.in_(event_ids)))
    conn.execute(delete(MapArchive).where(MapArchive.map_id == record.id, MapArchive.event_id.is_(None)))
    clear_map(conn=conn, map_id=record.id)
    if sessions:
        conn.execute(update(Job).where(Job.session_id.in_(sessions)).values(session_id=None))
        conn.execute(delete(MergeEventSession).where(MergeEventSession.session_id.in_(sessions)))
        conn.execute(delete(Evidence).where(Evidence.session_id.in_(sessions)))
        conn.execute(delete(Template).where(Template.session_id.in_(sessions)))
        conn.execute(delete(Session).where(Session.id.in_(sessions)))
    conn.execute(update(Job).where(Job.map_id == record.id).values(map_id=None))
    conn.execute(delete(Map).where(Map.id == record.id))
    return PurgeOutcome(record.name, len(sessions), len(event_ids))

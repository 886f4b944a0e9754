"""Merge events (issue 5): what was joined, how, and the archives that let it be undone.

The merger records an event first (:func:`record_merge_event`), then archives the pre-merge state of
every map involved with that ``event_id`` (:mod:`mapserver.store.archive`), then writes the merged map
— all in one write transaction. ``matches`` is free-form JSON; the suggested shape is
``{"templates": [{"target": id, "source": id, "target_uid": [session, index],
"source_uid": [session, index]}, ...], "experiences": [... the same ...]}`` (uids are stable identities).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any, cast

from sqlalchemy import Connection, func, insert, select, update

from mapserver.errors import NotFoundError, StoreError
from mapserver.statuses import MergeStatus
from mapserver.store.models import MERGE_STATUSES, MapArchive, MergeEvent, MergeEventSession, utcnow

MERGED_ARCHIVE_ROLE = "merged"
"""The role of the archive an unmerge takes of the merged map as it found it (``mapserver.store.archive``)."""


@dataclass(frozen=True)
class MergeEventSpec:
    """A merge to record.

    Attributes:
        map_id: the map the merge produced (the target).
        map_name: its name.
        mode: ``online`` (during ``process``) or ``offline`` (``mapserver merge``).
        confirmations: matching frames/templates that confirmed the merge.
        lattice_offset: pose-cell offset (cells) applied to the source, order (x, y, [z,] th).
        transform: SE(3) transform applied to the source's poses: (tx, ty, tz, qx, qy, qz, qw).
        yaw: the transform's rotation about z (radians).
        matches: the matched templates and experiences (see the module docstring).
        target_sessions: sessions of the target map before the merge.
        source_sessions: sessions joined into it.
        details: anything else worth keeping (thresholds, scores).
    """

    map_id: int
    map_name: str
    mode: str
    confirmations: int
    lattice_offset: Sequence[float]
    transform: Sequence[float]
    yaw: float
    matches: Mapping[str, Any]
    target_sessions: Sequence[int]
    source_sessions: Sequence[int]
    details: Mapping[str, Any] | None = None
    status: str = MergeStatus.APPLIED


@dataclass(frozen=True)
class MergeEventRecord:
    """A stored merge event with its sessions (id → role) and archive ids."""

    id: int
    map_id: int | None
    map_name: str
    mode: str
    status: str
    confirmations: int
    lattice_offset: list[float]
    transform: tuple[float, ...]
    yaw: float
    matches: dict[str, Any]
    details: dict[str, Any] | None
    created_at: datetime
    undone_at: datetime | None
    sessions: dict[int, str] = field(default_factory=dict)
    archive_ids: list[int] = field(default_factory=list)
    """The maps as they were before the merge (roles ``target`` and ``source``)."""
    merged_archive: int | None = None
    """The merged map as the last unmerge found it (role ``merged``; a redo restores it), None when none."""


def record_merge_event(*, conn: Connection, spec: MergeEventSpec) -> int:
    """Insert a merge event (status ``applied``, or ``rejected`` for one its verification rolled back); return its id.

    Raises:
        StoreError: the transform does not have 7 values, or an unknown status.
    """
    if spec.status not in MERGE_STATUSES:
        msg = f"merge status must be one of {MERGE_STATUSES!r}, got {spec.status!r}"
        raise StoreError(msg)
    if len(spec.transform) != 7:
        msg = f"a merge transform is (tx, ty, tz, qx, qy, qz, qw), got {len(spec.transform)} values"
        raise StoreError(msg)
    tx, ty, tz, qx, qy, qz, qw = (float(v) for v in spec.transform)
    event_id = conn.execute(
        insert(MergeEvent)
        .values(
            map_id=spec.map_id,
            map_name=spec.map_name,
            mode=spec.mode,
            status=spec.status,
            confirmations=int(spec.confirmations),
            lattice_offset=[float(v) for v in spec.lattice_offset],
            tx=tx, ty=ty, tz=tz, qx=qx, qy=qy, qz=qz, qw=qw,
            yaw=float(spec.yaw),
            matches=dict(spec.matches),
            details=None if spec.details is None else dict(spec.details),
            created_at=utcnow(),
        )
        .returning(MergeEvent.id)
    ).scalar_one()  # fmt: skip
    roles = {int(s): "target" for s in spec.target_sessions}
    roles.update({int(s): "source" for s in spec.source_sessions})
    if roles:
        conn.execute(
            insert(MergeEventSession),
            [{"event_id": event_id, "session_id": s, "role": r} for s, r in roles.items()],
        )
    return int(event_id)


def get_merge_event(*, conn: Connection, event_id: int) -> MergeEventRecord:
    """Return a merge event with its sessions and archives.

    Raises:
        NotFoundError: no such event.
    """
    events = _events(conn, MergeEvent.id == event_id)
    if not events:
        msg = f"no merge event with id {event_id!r}"
        raise NotFoundError(msg)
    return events[0]


def list_merge_events(*, conn: Connection, map_id: int | None = None) -> list[MergeEventRecord]:
    """Return the merge events (of one map when ``map_id`` is given), oldest first."""
    return _events(conn, None if map_id is None else MergeEvent.map_id == map_id)


def count_merge_events(*, conn: Connection) -> dict[str, int]:
    """Return ``{status: number of merge events}`` for the statuses that have any."""
    rows = conn.execute(select(MergeEvent.status, func.count()).group_by(MergeEvent.status)).all()
    return {str(r[0]): int(r[1]) for r in rows}


def set_merge_status(*, conn: Connection, event_id: int, status: str) -> None:
    """Mark a merge event ``undone`` (after unmerge) or ``applied`` again (after redo).

    Raises:
        StoreError: unknown status.
        NotFoundError: no such event.
    """
    if status not in MERGE_STATUSES:
        msg = f"merge status must be one of {MERGE_STATUSES!r}, got {status!r}"
        raise StoreError(msg)
    result = conn.execute(
        update(MergeEvent)
        .where(MergeEvent.id == event_id)
        .values(status=status, undone_at=utcnow() if status == MergeStatus.UNDONE else None)
    )
    if result.rowcount != 1:
        msg = f"no merge event with id {event_id!r}"
        raise NotFoundError(msg)


def update_merge_details(*, conn: Connection, event_id: int, details: Mapping[str, Any]) -> None:
    """Replace a merge event's ``details`` JSON (unmerge and redo note what they did there).

    Raises:
        NotFoundError: no such event.
    """
    result = conn.execute(update(MergeEvent).where(MergeEvent.id == event_id).values(details=dict(details)))
    if result.rowcount != 1:
        msg = f"no merge event with id {event_id!r}"
        raise NotFoundError(msg)


def _events(conn: Connection, where: Any) -> list[MergeEventRecord]:
    query = select(MergeEvent.__table__).order_by(MergeEvent.id)
    if where is not None:
        query = query.where(where)
    rows = conn.execute(query).all()
    if not rows:
        return []
    ids = [r.id for r in rows]
    sessions: dict[int, dict[int, str]] = {i: {} for i in ids}
    for event_id, session_id, role in conn.execute(
        select(MergeEventSession.event_id, MergeEventSession.session_id, MergeEventSession.role).where(
            MergeEventSession.event_id.in_(ids)
        )
    ).all():
        sessions[int(event_id)][int(session_id)] = str(role)
    archives: dict[int, list[int]] = {i: [] for i in ids}
    merged: dict[int, int] = {}
    for archive_id, owner, archive_role in conn.execute(
        select(MapArchive.id, MapArchive.event_id, MapArchive.role)
        .where(MapArchive.event_id.in_(ids))
        .order_by(MapArchive.id)
    ).all():
        if archive_role == MERGED_ARCHIVE_ROLE:
            merged[int(cast(int, owner))] = int(archive_id)  # the newest one
        else:
            archives[int(cast(int, owner))].append(int(archive_id))  # event_id IN ids: never NULL
    return [
        MergeEventRecord(
            id=int(r.id),
            map_id=r.map_id,
            map_name=r.map_name,
            mode=r.mode,
            status=r.status,
            confirmations=int(r.confirmations),
            lattice_offset=list(r.lattice_offset),
            transform=(r.tx, r.ty, r.tz, r.qx, r.qy, r.qz, r.qw),
            yaw=r.yaw,
            matches=dict(r.matches),
            details=None if r.details is None else dict(r.details),
            created_at=r.created_at,
            undone_at=r.undone_at,
            sessions=sessions[int(r.id)],
            archive_ids=archives[int(r.id)],
            merged_archive=merged.get(int(r.id)),
        )
        for r in rows
    ]

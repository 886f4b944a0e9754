"""Maps: create, find, list (with counts, or with parameters), claim for writing (optimistic version check), drop.

Lookups by name and listings see live maps only: an archived (deleted, restorable) map is found by
:mod:`mapserver.store.lifecycle`, which archives, restores, renames and purges maps.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import Any, NamedTuple, cast

from sqlalchemy import Connection, func, insert, select, update

from mapserver.statuses import MergeStatus
from mapserver.store.errors import MapExistsError, StaleMapError, UnknownMapError
from mapserver.store.models import (
    MERGE_STATUSES,
    Experience,
    Link,
    Map,
    MapState,
    MergeEvent,
    PoseCellLink,
    Session,
    Template,
    utcnow,
)


@dataclass(frozen=True, slots=True)
class MapRecord:
    """A stored map's row.

    Attributes:
        id: database id.
        name: unique name.
        version: write counter (incremented by every state write).
        params: the map's effective engine parameters (``Params.to_dict()``).
        created_at: creation time (UTC).
        updated_at: last state write (UTC).
        archived_at: when the map was deleted (archived; restorable), None for a live map.
    """

    id: int
    name: str
    version: int
    params: dict[str, Any]
    created_at: datetime
    updated_at: datetime
    archived_at: datetime | None = None


@dataclass(frozen=True, slots=True)
class MapSummary:
    """One line of the contract's ``maps`` listing."""

    name: str
    sessions: int
    templates: int
    experiences: int
    links: int
    #: {"residual", "switched_off", "links"} (mapserver.store.health); None for a state stored before it existed
    health: dict[str, Any] | None = None
    #: merge events that produced this map (or were rolled back in it), by status: applied, rejected, undone
    merges: dict[str, int] | None = None
    #: when the map was deleted (archived), None for a live map
    archived_at: datetime | None = None

    def as_dict(self) -> dict[str, Any]:
        """Return ``{"name", "sessions", "templates", "experiences", "links", "health", "merges"}``.

        An archived map's dict also holds ``archived_at`` (ISO 8601).
        """
        extra = {} if self.archived_at is None else {"archived_at": self.archived_at.isoformat()}
        return {
            "name": self.name,
            "sessions": self.sessions,
            "templates": self.templates,
            "experiences": self.experiences,
            "links": self.links,
            "health": self.health,
            "merges": dict(self.merges) if self.merges is not None else _no_merges(),
            **extra,
        }


class MapParams(NamedTuple):
    """A map's id, name, stored parameters (as stored: not checked) and version."""

    id: int
    name: str
    params: Any
    version: int


_COLUMNS = (Map.id, Map.name, Map.version, Map.params, Map.created_at, Map.updated_at, Map.archived_at)


def _record(row: Any) -> MapRecord:
    return MapRecord(int(row[0]), str(row[1]), int(row[2]), dict(row[3]), row[4], row[5], row[6])


def find_map(*, conn: Connection, name: str, archived: bool | None = False) -> MapRecord | None:
    """Return the map called ``name`` or None.

    ``archived``: False (the default) finds a live map only, True an archived one only, None either.
    """
    query = select(*_COLUMNS).where(Map.name == name)
    if archived is not None:
        query = query.where(Map.archived_at.is_not(None) if archived else Map.archived_at.is_(None))
    row = conn.execute(query).first()
    return None if row is None else _record(row)


def get_map(*, conn: Connection, name: str) -> MapRecord:
    """Return the map called ``name``.

    Raises:
        UnknownMapError: no such map (the message names no other map: ``mapserver maps`` and ``GET /v1/maps``
            list them to whoever may read them).
    """
    record = find_map(conn=conn, name=name)
    if record is None:
        msg = f"no map named {name!r} in this database"
        raise UnknownMapError(msg)
    return record


def get_map_by_id(*, conn: Connection, map_id: int) -> MapRecord:
    """Return the map with database id ``map_id``.

    Raises:
        UnknownMapError: no such map.
    """
    row = conn.execute(select(*_COLUMNS).where(Map.id == map_id)).first()
    if row is None:
        msg = f"no map with id {map_id!r}"
        raise UnknownMapError(msg)
    return _record(row)


def create_map(*, conn: Connection, name: str, params: Mapping[str, Any]) -> MapRecord:
    """Create an empty map (version 0; its state is written by :func:`~mapserver.store.state.write_map_state`).

    Raises:
        MapExistsError: the name is taken, by a live map or by an archived one (restore or purge it first).
    """
    holder = find_map(conn=conn, name=name, archived=None)
    if holder is not None:
        msg = (
            f"a map named {name!r} already exists"
            if holder.archived_at is None
            else f"the name {name!r} is held by an archived (deleted) map; restore it, or purge it for good first"
        )
        raise MapExistsError(msg)
    now = utcnow()
    map_id = conn.execute(
        insert(Map).values(name=name, version=0, params=dict(params), created_at=now, updated_at=now).returning(Map.id)
    ).scalar_one()
    return MapRecord(int(map_id), name, 0, dict(params), now, now)


ATLAS_LOCK_KEY = 0x6D617073  # "maps"
"""PostgreSQL advisory lock taken by :func:`lock_atlas`."""


def lock_atlas(*, conn: Connection) -> None:
    """Serialise the write transactions that decide which maps a session joins (until this transaction ends).

    SQLite write transactions hold the database write lock already (``BEGIN IMMEDIATE``); on
    PostgreSQL (READ COMMITTED) a transaction-level advisory lock makes a second writer wait, after
    which its statements see the first writer's committed maps.
    """
    if conn.dialect.name == "postgresql":
        conn.execute(select(func.pg_advisory_xact_lock(ATLAS_LOCK_KEY)))


def claim_map(*, conn: Connection, map_id: int, expected_version: int) -> int:
    """Bump the map's version if it is still ``expected_version``; return the new version.

    Call it first in a write transaction: on PostgreSQL the UPDATE locks the map row until commit (a
    concurrent writer blocks, then sees the new version and fails); on SQLite the transaction already
    holds the database write lock.

    Raises:
        StaleMapError: another writer changed the map since it was read, or deleted (archived) it.
        UnknownMapError: the map no longer exists.
    """
    result = conn.execute(
        update(Map)
        .where(Map.id == map_id, Map.version == expected_version, Map.archived_at.is_(None))
        .values(version=Map.version + 1, updated_at=utcnow())
    )
    if result.rowcount == 1:
        return expected_version + 1
    row = conn.execute(select(Map.name, Map.version, Map.archived_at).where(Map.id == map_id)).first()
    if row is None:
        msg = f"map id {map_id!r} was deleted by another writer"
        raise UnknownMapError(msg)
    if row[2] is not None:
        msg = f"map {row[0]!r} was deleted (archived) while this write was prepared; nothing was written"
        raise StaleMapError(msg)
    msg = (
        f"map {row[0]!r} was changed by another writer (version {row[1]}, expected {expected_version}); "
        "nothing was written"
    )
    raise StaleMapError(msg)


def list_maps(*, conn: Connection, archived: bool = False) -> list[MapSummary]:
    """Return every map with its session, template, experience and link counts, health and merges, by name.

    ``archived``: list the archived (deleted, restorable) maps instead of the live ones.
    """
    sessions = (
        select(Session.map_id, func.count().label("n")).where(Session.map_id.is_not(None)).group_by(Session.map_id)
    ).subquery()
    rows = conn.execute(
        select(
            Map.id,
            Map.name,
            func.coalesce(sessions.c.n, 0),
            func.coalesce(MapState.n_templates, 0),
            func.coalesce(MapState.n_experiences, 0),
            func.coalesce(MapState.n_links, 0),
            MapState.health,
            Map.archived_at,
        )
        .outerjoin(sessions, sessions.c.map_id == Map.id)
        .outerjoin(MapState, MapState.map_id == Map.id)
        .where(Map.archived_at.is_not(None) if archived else Map.archived_at.is_(None))
        .order_by(Map.name)
    ).all()
    merges = _merge_counts(conn)
    return [
        MapSummary(str(r[1]), int(r[2]), int(r[3]), int(r[4]), int(r[5]), r[6],
                   merges.get(int(r[0]), _no_merges()), r[7])
        for r in rows
    ]  # fmt: skip


def list_map_params(*, conn: Connection) -> list[MapParams]:
    """Return every live map's id, name, parameters and version, by id (no counts, no state)."""
    rows = conn.execute(
        select(Map.id, Map.name, Map.params, Map.version).where(Map.archived_at.is_(None)).order_by(Map.id)
    ).all()
    return [MapParams(r[0], r[1], r[2], r[3]) for r in rows]


def map_names(*, conn: Connection, map_ids: Collection[int]) -> dict[int, str]:
    """Return ``{id: name}`` of the maps among ``map_ids`` (ids that name no map are left out)."""
    rows = conn.execute(select(Map.id, Map.name).where(Map.id.in_(map_ids))).all()
    return {int(r[0]): str(r[1]) for r in rows}


def _no_merges() -> dict[str, int]:
    return {**dict.fromkeys(MERGE_STATUSES, 0), "unverified": 0}


def _merge_counts(conn: Connection) -> dict[int, dict[str, int]]:
    """Return per map id its merge events by status, and ``unverified``: applied ones the log ended in probation.

    An online merge's verification (``details.evidence.verification.status``) is ``incomplete`` when the log
    ended before its probation could conclude (``mapserver.merge.verify.Probation.conclude_at_end``).
    """
    merges: dict[int, dict[str, int]] = {}
    counted = select(MergeEvent.map_id, MergeEvent.status, func.count()).where(MergeEvent.map_id.is_not(None))
    for map_id, status, n in conn.execute(counted.group_by(MergeEvent.map_id, MergeEvent.status)):
        merges.setdefault(int(cast(int, map_id)), _no_merges())[str(status)] = int(n)
    applied = select(MergeEvent.map_id, MergeEvent.details).where(
        MergeEvent.map_id.is_not(None), MergeEvent.status == MergeStatus.APPLIED, MergeEvent.mode == "online"
    )
    for map_id, details in conn.execute(applied):
        verification = ((details or {}).get("evidence") or {}).get("verification") or {}
        if verification.get("status") == "incomplete":
            merges.setdefault(int(map_id), _no_merges())["unverified"] += 1
    return merges


def clear_map(*, conn: Connection, map_id: int) -> None:
    """Empty a map's content (experiences, links, pose-cell links, state) and detach its templates.

    The map row, its version and its sessions stay; template rows stay too, detached (``map_id`` NULL),
    because archived map states refer to them.
    """
    for table in (Link, PoseCellLink, Experience, MapState):
        conn.execute(table.__table__.delete().where(table.map_id == map_id))
    conn.execute(update(Template).where(Template.map_id == map_id).values(map_id=None, local_id=None))


def drop_map(*, conn: Connection, map_id: int) -> None:
    """Delete a map: its content goes (see :func:`clear_map`), its sessions are detached (``map_id`` NULL).

    Use it when a merge joins this map into another one, after archiving it.
    """
    clear_map(conn=conn, map_id=map_id)
    conn.execute(update(Session).where(Session.map_id == map_id).values(map_id=None))
    conn.execute(Map.__table__.delete().where(Map.id == map_id))

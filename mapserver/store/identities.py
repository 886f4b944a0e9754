"""Stable identities of templates and experiences: where each lives now, and how far each session's indices reached.

A template or experience is named for good by (origin session, origin index); a merge renumbers its map-local id
(``local_id``) and may move it to another map. These queries answer, for identities that merges, reports and the
viewer hold, which map and map-local id they have today, and the highest index a session ever used (so new rows
never reuse one).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple, cast

from sqlalchemy import Connection, func, select, tuple_

from mapserver.store.models import Evidence, Experience, Map, Session, Template

Identity = tuple[int, int]
"""(origin session id, origin index)."""


class PlacedExperience(NamedTuple):
    """An experience where it is now: its map's name, its id in that map, its session's name and its position."""

    map: str
    id: int
    session: str
    x: float
    y: float
    z: float


def index_maxima(*, conn: Connection, session_ids: Sequence[int]) -> dict[int, tuple[int, int]]:
    """Return session → (1 + largest template index, 1 + largest experience/evidence index) stored anywhere.

    Every session of ``session_ids`` has an entry; (0, 0) for one with no rows.
    """
    out: dict[int, list[int]] = {int(s): [0, 0] for s in session_ids}
    if not out:
        return {}
    ids = list(out)
    for table, axis in ((Template, 0), (Experience, 1), (Evidence, 1)):
        rows = conn.execute(
            select(table.session_id, func.max(table.origin_index)).where(table.session_id.in_(ids))
            .group_by(table.session_id)
        ).all()  # fmt: skip
        for sid, top in rows:
            if top is not None:
                out[int(sid)][axis] = max(out[int(sid)][axis], int(top) + 1)
    return {k: (v[0], v[1]) for k, v in out.items()}


def template_ids_matching(
    *, conn: Connection, map_id: int, session_ids: Sequence[int], origin_indices: Sequence[int]
) -> list[int]:
    """Return the map-local ids of map ``map_id``'s templates with a session and an origin index among these.

    ``session_ids`` and ``origin_indices`` are matched each on its own, not as pairs; the database's order.
    """
    rows = conn.execute(
        select(Template.local_id).where(
            Template.map_id == map_id,
            Template.session_id.in_(session_ids),
            Template.origin_index.in_(origin_indices),
        )
    ).all()
    return [int(cast(int, r[0])) for r in rows]  # a template in a map has its local id


def template_ids_by_identity(*, conn: Connection, map_id: int) -> dict[Identity, int]:
    """Return ``{(origin session, origin index): map-local id}`` of map ``map_id``'s templates."""
    rows = conn.execute(
        select(Template.session_id, Template.origin_index, Template.local_id).where(Template.map_id == map_id)
    ).all()
    return {(int(r[0]), int(r[1])): int(r[2]) for r in rows if r[2] is not None}


def _placed(row: Sequence[Any]) -> PlacedExperience:
    return PlacedExperience(row[0], int(row[1]), row[2], row[3], row[4], row[5])


def experiences_at(*, conn: Connection, uids: Sequence[Identity]) -> dict[Identity, PlacedExperience]:
    """Return, per stable experience identity among ``uids``, where that experience is now.

    Identities of no stored experience are left out.
    """
    if not uids:
        return {}
    rows = conn.execute(
        select(Experience.session_id, Experience.origin_index, Map.name, Experience.local_id, Session.name,
               Experience.x, Experience.y, Experience.z)
        .join(Map, Map.id == Experience.map_id).join(Session, Session.id == Experience.session_id)
        .where(tuple_(Experience.session_id, Experience.origin_index).in_(uids))
    ).all()  # fmt: skip
    return {(int(r[0]), int(r[1])): _placed(r[2:]) for r in rows}


def template_users(*, conn: Connection, uids: Sequence[Identity]) -> dict[Identity, list[PlacedExperience]]:
    """Return, per stable template identity among ``uids`` held by a map, the experiences that use it now.

    The experiences may be of any session; by map-local id; one query per template found.
    """
    if not uids:
        return {}
    found = conn.execute(
        select(Template.session_id, Template.origin_index, Template.map_id, Template.local_id)
        .where(tuple_(Template.session_id, Template.origin_index).in_(uids), Template.map_id.is_not(None))
    ).all()  # fmt: skip
    out: dict[Identity, list[PlacedExperience]] = {}
    for sid, index, map_id, local in found:
        rows = conn.execute(
            select(Map.name, Experience.local_id, Session.name, Experience.x, Experience.y, Experience.z)
            .join(Map, Map.id == Experience.map_id).join(Session, Session.id == Experience.session_id)
            .where(Experience.map_id == map_id, Experience.template == local)
            .order_by(Experience.local_id)
        ).all()  # fmt: skip
        out[(int(sid), int(index))] = [_placed(r) for r in rows]
    return out

"""Read-only queries that need no full map state: paged experiences, the graph, the viewer's rows, counts."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from sqlalchemy import Connection, bindparam, case, func, select

from mapserver.errors import InputError
from mapserver.formats import LINK_KIND_CODES
from mapserver.store.bulk import fetch_tuples
from mapserver.store.models import Experience, Link, Map, MapState, Session

MAX_PAGE = 10_000
# built once: a cached statement; an archived (deleted) map is no map here
_MAP_VERSION = select(Map.id, Map.version).where(Map.name == bindparam("name"), Map.archived_at.is_(None))


def page_experiences(
    *, conn: Connection, map_id: int, offset: int = 0, limit: int = 100
) -> tuple[list[dict[str, Any]], int]:
    """Return one page of a map's experiences by id, and the total count.

    Each item is ``{"id", "x", "y", "z", "qx", "qy", "qz", "qw", "yaw", "template", "stamp", "session"}``
    (``session`` is the session name), served by the experiences primary key (map_id, local_id).

    Raises:
        InputError: negative offset, or limit outside 1..MAX_PAGE.
    """
    if offset < 0 or not 1 <= limit <= MAX_PAGE:
        msg = f"offset must be ≥ 0 and limit in 1..{MAX_PAGE}, got offset={offset!r} limit={limit!r}"
        raise InputError(msg)
    count = select(func.count()).select_from(Experience).where(Experience.map_id == map_id)
    total = int(conn.execute(count).scalar_one())
    rows = conn.execute(
        select(
            Experience.local_id, Experience.x, Experience.y, Experience.z, Experience.qx, Experience.qy,
            Experience.qz, Experience.qw, Experience.yaw, Experience.template, Experience.stamp, Session.name,
        )
        .join(Session, Session.id == Experience.session_id)
        .where(Experience.map_id == map_id)
        .order_by(Experience.local_id)
        .offset(offset)
        .limit(limit)
    ).all()  # fmt: skip
    keys = ("id", "x", "y", "z", "qx", "qy", "qz", "qw", "yaw", "template", "stamp", "session")
    return [dict(zip(keys, row, strict=True)) for row in rows], total


@dataclass(frozen=True)
class Graph:
    """A map's experience graph: poses (E, 4) x, y, z, yaw and links (K,) from, to, dt, distance, kind."""

    poses: npt.NDArray[np.float64]
    link_from: npt.NDArray[np.int64]
    link_to: npt.NDArray[np.int64]
    link_dt: npt.NDArray[np.float64]
    link_distance: npt.NDArray[np.float64]
    link_kind: npt.NDArray[np.int64]


def load_graph(*, conn: Connection, map_id: int) -> Graph:
    """Return a map's experience graph without reading templates or engine state (path queries)."""
    poses = np.array(
        fetch_tuples(
            conn,
            select(Experience.x, Experience.y, Experience.z, Experience.yaw)
            .where(Experience.map_id == map_id)
            .order_by(Experience.local_id),
        ),
        dtype=np.float64,
    ).reshape(-1, 4)
    kind_code = case(LINK_KIND_CODES, value=Link.kind, else_=-1)
    links = np.array(
        fetch_tuples(
            conn,
            select(Link.from_id, Link.to_id, Link.dt, Link.distance, kind_code)
            .where(Link.map_id == map_id)
            .order_by(Link.seq),
        ),
        dtype=np.float64,
    ).reshape(-1, 5)
    return Graph(
        poses=poses,
        link_from=links[:, 0].astype(np.int64),
        link_to=links[:, 1].astype(np.int64),
        link_dt=links[:, 2].copy(),
        link_distance=links[:, 3].copy(),
        link_kind=links[:, 4].astype(np.int64),
    )


def map_version(*, conn: Connection, name: str) -> tuple[int, int] | None:
    """Return ``(map id, version)`` of map ``name``, None when there is none: one indexed lookup, no JSON."""
    row = conn.execute(_MAP_VERSION, {"name": name}).first()
    return None if row is None else (int(row[0]), int(row[1]))


def view_experiences(*, conn: Connection, map_id: int) -> list[tuple[Any, ...]]:
    """Return ``(x, y, z, yaw, session id, template, stamp)`` of a map's experiences, by id (the web viewer)."""
    return fetch_tuples(
        conn,
        select(Experience.x, Experience.y, Experience.z, Experience.yaw, Experience.session_id,
               Experience.template, Experience.stamp)
        .where(Experience.map_id == map_id)
        .order_by(Experience.local_id),
    )  # fmt: skip


def view_links(*, conn: Connection, map_id: int) -> list[tuple[Any, ...]]:
    """Return ``(from, to, dt, distance, kind name, active)`` of a map's links, in link order (the web viewer)."""
    rows = conn.execute(
        select(Link.from_id, Link.to_id, Link.dt, Link.distance, Link.kind, Link.active)
        .where(Link.map_id == map_id)
        .order_by(Link.seq)
    ).all()
    return [tuple(r) for r in rows]


def map_state_counts(*, conn: Connection, map_id: int) -> tuple[int, int, int] | None:
    """Return ``(templates, experiences, links)`` of a map's stored state, None when it has no state row."""
    row = conn.execute(
        select(MapState.n_templates, MapState.n_experiences, MapState.n_links).where(MapState.map_id == map_id)
    ).first()
    return None if row is None else (int(row[0]), int(row[1]), int(row[2]))


def count_links(*, conn: Connection, map_id: int, kind: str) -> int:
    """Return the number of a map's links of one kind (``odometry``, ``loop``, ``merge`` or ``manual``)."""
    counted = select(func.count()).select_from(Link).where(Link.map_id == map_id, Link.kind == kind)
    return int(conn.execute(counted).scalar_one())

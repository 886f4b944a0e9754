"""A map's manual links as stored: each with its status, its transform, and the event that added it (author, time).

A manual link is a row of ``links`` of kind ``manual``; the merge event (mode ``manual``) that added it names its
ends by their stable identities (``details.link.from_uid`` / ``to_uid``: origin session and index), so the link
is found in whichever map holds it today, with the ids it has there.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import Connection, select

from mapserver.statuses import MergeStatus
from mapserver.store.merge_events import list_merge_events
from mapserver.store.models import Experience, Link

MANUAL_EVENT_MODE = "manual"


@dataclass(frozen=True)
class StoredManualLink:
    """A manual link of a map: ends (map-local ids), transform (dx, dy, dz, dyaw), status, and who added it when."""

    seq: int
    from_id: int
    to_id: int
    transform: tuple[float, float, float, float]
    active: bool
    event: int | None
    author: str | None
    created_at: datetime | None

    def as_dict(self) -> dict[str, Any]:
        """Return the link as ``GET /v1/maps/{name}/links`` gives it."""
        dx, dy, dz, dyaw = self.transform
        return {
            "link": self.seq, "from": self.from_id, "to": self.to_id, "kind": "manual", "active": self.active,
            "dx": dx, "dy": dy, "dz": dz, "dyaw": dyaw, "event": self.event, "author": self.author,
            "created_at": None if self.created_at is None else self.created_at.isoformat(),
        }  # fmt: skip


def _identities(conn: Connection, map_id: int, ids: set[int]) -> dict[int, tuple[int, int]]:
    """Return map-local experience id → (origin session, origin index) for ``ids``."""
    if not ids:
        return {}
    rows = conn.execute(
        select(Experience.local_id, Experience.session_id, Experience.origin_index)
        .where(Experience.map_id == map_id, Experience.local_id.in_(sorted(ids)))
    ).all()  # fmt: skip
    return {int(r[0]): (int(r[1]), int(r[2])) for r in rows}


def _events_by_ends(conn: Connection) -> dict[tuple[tuple[int, int], tuple[int, int]], Any]:
    """Return the applied manual-link events by the stable identities of their ends (the latest for a pair)."""
    out: dict[tuple[tuple[int, int], tuple[int, int]], Any] = {}
    for event in list_merge_events(conn=conn):
        link = (event.details or {}).get("link") or {}
        if event.mode != MANUAL_EVENT_MODE or event.status != MergeStatus.APPLIED or "from_uid" not in link:
            continue
        ends = (tuple(int(v) for v in link["from_uid"]), tuple(int(v) for v in link["to_uid"]))
        out[ends] = event  # type: ignore[index]
    return out


def manual_links(*, conn: Connection, map_id: int) -> list[StoredManualLink]:
    """Return a map's manual links in link order, each with the event that added it (None if none is applied)."""
    rows = conn.execute(
        select(Link.seq, Link.from_id, Link.to_id, Link.dx, Link.dy, Link.dz, Link.dyaw, Link.active)
        .where(Link.map_id == map_id, Link.kind == "manual")
        .order_by(Link.seq)
    ).all()  # fmt: skip
    if not rows:
        return []
    uids = _identities(conn, map_id, {int(r[1]) for r in rows} | {int(r[2]) for r in rows})
    events = _events_by_ends(conn)
    out = []
    for seq, a, b, dx, dy, dz, dyaw, active in rows:
        event = events.get((uids.get(int(a), (-1, -1)), uids.get(int(b), (-1, -1))))
        out.append(StoredManualLink(
            int(seq), int(a), int(b), (float(dx), float(dy), float(dz), float(dyaw)), bool(active),
            None if event is None else event.id,
            None if event is None else str(event.details["link"].get("author")),
            None if event is None else event.created_at,
        ))  # fmt: skip
    return out


__all__ = ["MANUAL_EVENT_MODE", "StoredManualLink", "manual_links"]

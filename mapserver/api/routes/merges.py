"""``/v1/merges``: merge events with their matched places located in today's maps; undo and redo (write)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path, Query
from starlette.concurrency import run_in_threadpool

from mapserver.api.deps import ReadAccess, ServicesDep, WriteAccess
from mapserver.api.routes.maps import AUTH_ERRORS, MAX_ID
from mapserver.api.schemas import ErrorPublic
from mapserver.api.services import Services
from mapserver.atlas.undo import redo_merge, unmerge
from mapserver.store import Connection, get_map
from mapserver.store.identities import PlacedExperience, experiences_at, template_users
from mapserver.store.merge_events import MergeEventRecord, get_merge_event, list_merge_events
from mapserver.store.sessions import get_sessions

router = APIRouter(prefix="/v1/merges", tags=["merges"])
EVENT_ERRORS: dict[int | str, dict[str, Any]] = {**AUTH_ERRORS, 404: {"model": ErrorPublic}}
WRITE_ERRORS: dict[int | str, dict[str, Any]] = {**EVENT_ERRORS, 409: {"model": ErrorPublic}}
EventId = Annotated[int, Path(ge=1, le=MAX_ID, description="merge event id")]


def _experiences_at(conn: Connection, uids: list[tuple[int, int]]) -> dict[tuple[int, int], list[dict[str, Any]]]:
    """Return, per stable experience identity (session, index), where it lives now: map, id, session, pose."""
    return {uid: [_node(p)] for uid, p in experiences_at(conn=conn, uids=uids).items()}


def _node(placed: PlacedExperience) -> dict[str, Any]:
    return {"map": placed.map, "id": placed.id, "session": placed.session, "x": placed.x, "y": placed.y,
            "z": placed.z}  # fmt: skip


def _template_users(conn: Connection, uids: list[tuple[int, int]]) -> dict[tuple[int, int], list[dict[str, Any]]]:
    """Return, per stable template identity, the experiences (any session) that use that template now."""
    return {uid: [_node(p) for p in placed] for uid, placed in template_users(conn=conn, uids=uids).items()}


def _groups(conn: Connection, pairs: list[dict[str, Any]], what: str) -> list[dict[str, Any]]:
    """Return one place per identified pair: the experiences that stand for it today (both sessions)."""
    pairs = [p for p in pairs if "target_uid" in p and "source_uid" in p]
    uids = sorted({(int(p[k][0]), int(p[k][1])) for p in pairs for k in ("target_uid", "source_uid")})
    where = _template_users(conn, uids) if what == "template" else _experiences_at(conn, uids)
    groups = []
    for p in pairs:
        nodes = {(n["map"], n["id"]): n for k in ("target_uid", "source_uid")
                 for n in where.get((int(p[k][0]), int(p[k][1])), [])}  # fmt: skip
        groups.append({"kind": what, "target_uid": p["target_uid"], "source_uid": p["source_uid"],
                       "nodes": list(nodes.values())})  # fmt: skip
    return groups


def event_view(conn: Connection, event: MergeEventRecord) -> dict[str, Any]:
    """Return a merge event for the viewer: status, sessions by name, transform, and its matched places.

    ``places`` has one entry per identified template pair and per identified experience pair, with the
    experiences that stand for that place today (in whichever map holds them: after an undo the two
    sessions' experiences are in two maps again), so the viewer can mark the place in both sessions.
    """
    involved = sorted(event.sessions)
    names = {s.id: s.name for s in get_sessions(conn=conn, session_ids=involved)} if involved else {}
    matches = event.matches or {}
    places = _groups(conn, matches.get("templates", []), "template") + _groups(
        conn, matches.get("experiences", []), "experience"
    )
    details = event.details or {}
    return {
        "id": event.id, "map": event.map_name, "mode": event.mode, "status": event.status,
        "confirmations": event.confirmations, "created_at": event.created_at.isoformat(),
        "undone_at": None if event.undone_at is None else event.undone_at.isoformat(),
        "sessions": {names.get(s, str(s)): role for s, role in event.sessions.items()},
        "transform": list(event.transform), "yaw": event.yaw, "lattice_offset": list(event.lattice_offset),
        "anchor": matches.get("anchor"), "places": places,
        "reason": ((details.get("evidence") or {}).get("verification") or {}).get("reason"),
        "evidence": details.get("evidence"),
        "link": details.get("link"),  # a manual link's: ends, transform, author, whether the check kept it on
    }  # fmt: skip


def _list(services: Services, map_name: str | None) -> list[dict[str, Any]]:
    with services.db.read() as conn:
        events = list_merge_events(conn=conn)
        if map_name is not None:
            record = get_map(conn=conn, name=map_name)
            mine = {s for e in events if e.map_id == record.id or e.map_name == record.name for s in e.sessions}
            events = [e for e in events if e.map_id == record.id or e.map_name == record.name or set(e.sessions) & mine]
        return [event_view(conn, e) for e in events]


@router.get("", operation_id="list_merges", responses=EVENT_ERRORS)
async def read_merges(
    services: ServicesDep,
    _token: ReadAccess,
    map: Annotated[str | None, Query(min_length=1, max_length=200, description="only this map's events")] = None,
) -> dict[str, Any]:
    """List merge events (applied, rejected, undone), oldest first, with their matched places."""
    return {"merges": await run_in_threadpool(_list, services, map)}


def _one(services: Services, event_id: int) -> dict[str, Any]:
    with services.db.read() as conn:
        return event_view(conn, get_merge_event(conn=conn, event_id=event_id))


@router.get("/{event}", operation_id="get_merge", responses=EVENT_ERRORS)
async def read_merge(event: EventId, services: ServicesDep, _token: ReadAccess) -> dict[str, Any]:
    """Return one merge event with its matched places."""
    return await run_in_threadpool(_one, services, event)


@router.post("/{event}/undo", operation_id="undo_merge", responses=WRITE_ERRORS)
async def undo_merge(
    event: EventId,
    services: ServicesDep,
    _token: WriteAccess,
    rewind: Annotated[bool, Query(description="leave an online merge's session partial at its merge frame")] = False,
) -> dict[str, Any]:
    """Undo an applied merge: its maps are restored as they were before it (409 when that would lose work).

    An online merge's session keeps the frames it had at the merge (``frames``): complete there, or partial
    with ``rewind`` (``session_status``).
    """
    outcome = await run_in_threadpool(unmerge, services.db, event_id=event, rewind=rewind)
    body = await run_in_threadpool(_one, services, event)
    return {**body, "maps": outcome.maps, "session_rewound": outcome.session_rewound, "frames": outcome.frames,
            "session_status": outcome.session_status}  # fmt: skip


@router.post("/{event}/redo", operation_id="redo_merge", responses=WRITE_ERRORS)
async def redo(event: EventId, services: ServicesDep, _token: WriteAccess) -> dict[str, Any]:
    """Apply an undone merge again, exactly as the first time (409 when its maps changed since the undo)."""
    outcome = await run_in_threadpool(redo_merge, services.db, event_id=event)
    body = await run_in_threadpool(_one, services, event)
    return {**body, "maps": [outcome.map_name]}

"""``/v1/maps``: list, one map, paged experiences, shortest paths, export; delete, restore, rename (write)."""

from __future__ import annotations

import time
from collections.abc import AsyncIterator, Callable
from functools import partial
from typing import Annotated, Any, Literal

import anyio
from fastapi import APIRouter, Body, Path, Query, Request
from fastapi.responses import Response, StreamingResponse
from pydantic_core import to_json
from starlette.concurrency import run_in_threadpool
from starlette.types import Send

from core.paths import PathResult
from mapserver.api.deps import ReadAccess, ServicesDep, WriteAccess
from mapserver.api.metrics import PATH_SECONDS
from mapserver.api.schemas import (
    ErrorPublic,
    ExperiencePublic,
    ExperiencesPublic,
    MapChangePublic,
    MapPublic,
    MapRenamePublic,
    MapsPublic,
    MapSummaryPublic,
    MergeEventPublic,
    PathPublic,
    SessionPublic,
)
from mapserver.store import get_map, list_maps, sessions_of_map
from mapserver.store.export import read_plot_graph, render_png
from mapserver.store.lifecycle import archive_map, purge_map, rename_map, restore_map
from mapserver.store.merge_events import list_merge_events
from mapserver.store.queries import MAX_PAGE, page_experiences
from mapserver.store.sessions import get_sessions
from mapserver.store.streams import ExportStream, open_export

router = APIRouter(prefix="/v1/maps", tags=["maps"])

AUTH_ERRORS: dict[int | str, dict[str, Any]] = {401: {"model": ErrorPublic}, 403: {"model": ErrorPublic}}
MAP_ERRORS: dict[int | str, dict[str, Any]] = {**AUTH_ERRORS, 404: {"model": ErrorPublic}}
MAX_ID = 2**62
MapName = Annotated[str, Path(min_length=1, max_length=200, description="the map's name")]
EXPORT_TYPES = {"json": "application/json", "tum": "text/plain; charset=utf-8", "png": "image/png",
                "g2o": "text/plain; charset=utf-8", "csv": "text/csv; charset=utf-8"}


# a live map's entry has no ``archived_at`` (the key is set for archived maps only)
@router.get("", operation_id="list_maps", response_model=MapsPublic, responses=AUTH_ERRORS,
            response_model_exclude_unset=True)  # fmt: skip
def read_maps(
    services: ServicesDep,
    _token: ReadAccess,
    archived: Annotated[bool, Query(description="list the archived (deleted, restorable) maps instead")] = False,
) -> MapsPublic:
    """List the stored maps with their session, template, experience and link counts (or the archived ones)."""
    with services.db.read() as conn:
        maps = list_maps(conn=conn, archived=archived)
    return MapsPublic(maps=[MapSummaryPublic(**m.as_dict()) for m in maps])


WRITE_MAP_ERRORS: dict[int | str, dict[str, Any]] = {**MAP_ERRORS, 409: {"model": ErrorPublic}}


@router.delete("/{name}", operation_id="delete_map", response_model=MapChangePublic, responses=WRITE_MAP_ERRORS)
def delete_map(
    name: MapName,
    services: ServicesDep,
    _token: WriteAccess,
    purge: Annotated[bool, Query(description="delete an archived map for good (its sessions and merges too)")] = False,
) -> MapChangePublic:
    """Delete a map: it is archived (hidden, restorable with ``POST .../restore``), nothing of it is lost.

    ``purge=true`` deletes an archived map for good: its content, sessions and the merge events that involve
    it. 409: the map is archived already (without ``purge``), live (with ``purge``), or a queued or running
    job processes a log into it.
    """
    with services.db.write() as conn:
        if purge:
            outcome = purge_map(conn=conn, name=name)
            return MapChangePublic(map=outcome.name, status="purged", sessions=outcome.sessions,
                                   merge_events=outcome.merge_events)  # fmt: skip
        record = archive_map(conn=conn, name=name)
    return MapChangePublic(map=record.name, status="archived", archived_at=record.archived_at)


@router.post(
    "/{name}/restore", operation_id="restore_map", response_model=MapChangePublic, responses=WRITE_MAP_ERRORS
)
def restore(name: MapName, services: ServicesDep, _token: WriteAccess) -> MapChangePublic:
    """Bring a deleted (archived) map back, exactly as it was; 409 when the map is not archived."""
    with services.db.write() as conn:
        record = restore_map(conn=conn, name=name)
    return MapChangePublic(map=record.name, status="live")


@router.patch(
    "/{name}", operation_id="rename_map", response_model=MapChangePublic,
    responses={**WRITE_MAP_ERRORS, 400: {"model": ErrorPublic}},
)  # fmt: skip
def rename(
    name: MapName, body: Annotated[MapRenamePublic, Body()], services: ServicesDep, _token: WriteAccess
) -> MapChangePublic:
    """Rename a map (``{"name": NEW}``); 400 a name that breaks the rule, 409 a name taken (an archived map's too)."""
    with services.db.write() as conn:
        record = rename_map(conn=conn, name=name, new_name=body.name)
    return MapChangePublic(map=record.name, status="live", previous=name)


@router.get("/{name}", operation_id="get_map", response_model=MapPublic, responses=MAP_ERRORS)
def read_map(name: MapName, services: ServicesDep, _token: ReadAccess) -> MapPublic:
    """Return one map: counts, effective parameters, its sessions and the merge events that built it."""
    with services.db.read() as conn:
        record = get_map(conn=conn, name=name)
        summary = next(m for m in list_maps(conn=conn) if m.name == record.name)
        sessions = sessions_of_map(conn=conn, map_id=record.id)
        events = list_merge_events(conn=conn, map_id=record.id)
        involved = sorted({s for e in events for s in e.sessions})
        names = {s.id: s.name for s in get_sessions(conn=conn, session_ids=involved)} if involved else {}
    return MapPublic(
        name=record.name,
        version=record.version,
        templates=summary.templates,
        experiences=summary.experiences,
        links=summary.links,
        health=summary.health,
        created_at=record.created_at,
        updated_at=record.updated_at,
        params=record.params,
        sessions=[
            SessionPublic(
                name=s.name, log_name=s.log_name, log_sha256=s.log_sha256, source=s.source, status=s.status,
                frames=s.frames_processed, frames_total=s.frames_total, first_stamp=s.first_stamp,
                last_stamp=s.last_stamp, started_at=s.started_at, finished_at=s.finished_at,
                frames_per_s=s.frames_per_s,
            )
            for s in sessions
        ],
        merge_events=[
            MergeEventPublic(
                id=e.id, mode=e.mode, status=e.status, confirmations=e.confirmations, created_at=e.created_at,
                undone_at=e.undone_at, sessions={names.get(s, str(s)): role for s, role in e.sessions.items()},
                transform=list(e.transform), yaw=e.yaw, lattice_offset=list(e.lattice_offset), matches=e.matches,
            )
            for e in events
        ],
    )


@router.get(
    "/{name}/experiences", operation_id="list_experiences", response_model=ExperiencesPublic, responses=MAP_ERRORS
)
def read_experiences(
    name: MapName,
    services: ServicesDep,
    _token: ReadAccess,
    offset: Annotated[int, Query(ge=0, le=MAX_ID, description="first experience (by id)")] = 0,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE, description="page size")] = 100,
) -> ExperiencesPublic:
    """Return one page of a map's experiences, by id, and their total."""
    with services.db.read() as conn:
        record = get_map(conn=conn, name=name)
        items, total = page_experiences(conn=conn, map_id=record.id, offset=offset, limit=limit)
    return ExperiencesPublic(
        experiences=[
            ExperiencePublic(
                id=i["id"], x=i["x"], y=i["y"], z=i["z"], yaw=i["yaw"], template=i["template"], session=i["session"],
                stamp=i["stamp"],
            )
            for i in items
        ],
        total=total,
        offset=offset,
        limit=limit,
    )


@router.get(
    "/{name}/path",
    operation_id="find_path",
    response_model=PathPublic,
    responses={**MAP_ERRORS, 409: {"model": ErrorPublic}},
)
async def read_path(
    name: MapName,
    services: ServicesDep,
    _token: ReadAccess,
    source: Annotated[int, Query(alias="from", ge=0, le=MAX_ID, description="start experience id")],
    target: Annotated[int, Query(alias="to", ge=0, le=MAX_ID, description="goal experience id")],
    weight: Annotated[Literal["time", "distance"], Query(description="minimise travel time or distance")] = "time",
) -> Response:
    """Return the shortest path between two experiences over the map's experience graph.

    404 when the map or an experience does not exist, 409 when the two are not connected.
    """
    # on the event loop: the version lookup and the search (each well under a millisecond on a cached
    # map); a load and build of the graph goes to a worker thread
    started = time.perf_counter()
    try:
        entry = services.graphs.current(name)
        if entry is None:
            entry = await run_in_threadpool(services.graphs.get, name)
        result = entry.path(source, target, weight)
        return Response(_path_json(result), media_type="application/json")
    finally:
        PATH_SECONDS.observe(time.perf_counter() - started)


def _path_json(result: PathResult) -> bytes:
    """Return ``PathPublic`` as JSON, serialised in one call (non-finite numbers as null, as pydantic does)."""
    poses = [{"x": x, "y": y, "z": z, "yaw": yaw} for x, y, z, yaw in result.poses.tolist()]
    body = {"nodes": result.nodes, "poses": poses, "cost": result.cost, "weight": result.weight}
    return to_json(body, inf_nan_mode="null")


@router.get(
    "/{name}/export",
    operation_id="export_map",
    responses={
        **MAP_ERRORS,
        409: {"model": ErrorPublic, "description": "JSON of a map holding an infinite number"},
        503: {"model": ErrorPublic, "description": "as many exports run as the server allows (see Retry-After)",
              "headers": {"Retry-After": {"description": "seconds to wait", "schema": {"type": "integer"}}}},
        200: {
            "content": {"application/json": {}, "text/plain": {}, "text/csv": {}, "image/png": {}},
            "description": "the map as map JSON (mapserver-map/1), TUM poses, g2o, a CSV table or a PNG plot",
        },
    },
    response_class=Response,
)
async def read_export(
    name: MapName,
    request: Request,
    services: ServicesDep,
    _token: ReadAccess,
    format: Annotated[Literal["json", "tum", "png", "g2o", "csv"], Query(description="the format")] = "json",
    table: Annotated[Literal["experiences", "links"], Query(description="csv: which table")] = "experiences",
) -> Response:
    """Return a stored map as map JSON, TUM experience poses (stamp order), g2o, a CSV table or a PNG plot.

    JSON, TUM, g2o and CSV are streamed from the database a batch of rows at a time (the same bytes as
    ``mapserver export``); at most ``--max-exports`` exports run at once, more are answered 503.
    """
    slots = request.app.state.export_slots
    release = slots.acquire()
    headers = {"Content-Disposition": f"inline; filename*=UTF-8''{_quote(_filename(name, format, table))}"}
    if format == "png":
        try:
            graph = await run_in_threadpool(partial(read_plot_graph, services.db, name=name))
            body = await run_in_threadpool(render_png, graph)
        finally:
            release()
        return Response(body, media_type=EXPORT_TYPES[format], headers=headers)
    try:
        fmt = "links.csv" if format == "csv" and table == "links" else format
        stream = await anyio.to_thread.run_sync(partial(open_export, services.db, name=name, fmt=fmt),
                                                limiter=slots.threads)  # fmt: skip
    except BaseException:
        release()
        raise
    return ExportResponse(stream, release, slots.threads, media_type=EXPORT_TYPES[format], headers=headers)


def _filename(name: str, format: str, table: str) -> str:
    suffix = {"tum": "txt", "csv": "links.csv" if table == "links" else "csv"}.get(format, format)
    return f"{name}.{suffix}"


class ExportResponse(StreamingResponse):
    """A streamed export: chunks formatted in the export threads; its read ends and its slot frees at its end."""

    def __init__(
        self, stream: ExportStream, release: Callable[[], None], threads: anyio.CapacityLimiter, **kwargs: Any
    ) -> None:
        self._stream = stream
        self._release = release
        self._threads = threads
        super().__init__(self._chunks(), **kwargs)

    async def _chunks(self) -> AsyncIterator[bytes]:
        while (chunk := await anyio.to_thread.run_sync(next, self._stream, None, limiter=self._threads)) is not None:
            yield chunk

    async def stream_response(self, send: Send) -> None:
        """Send the chunks; then (sent, failed or the client gone) close the stream and free the slot."""
        try:
            await super().stream_response(send)
        finally:
            with anyio.CancelScope(shield=True):
                await run_in_threadpool(self._stream.close)
            self._release()


def _quote(text: str) -> str:
    from urllib.parse import quote

    return quote(text, safe="")

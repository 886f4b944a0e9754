"""Viewer reads of ``/v1/maps/{name}``: the graph decimated for a viewport, nearest node, node details, evidence."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Path, Query, Request
from fastapi.responses import Response
from pydantic_core import to_json
from starlette.concurrency import run_in_threadpool

from mapserver.api.deps import ReadAccess, ServicesDep
from mapserver.api.routes.maps import MAP_ERRORS, MAX_ID, MapName
from mapserver.api.schemas import ErrorPublic
from mapserver.api.services import Services
from mapserver.api.viewdata import MAX_NODES, ViewCache, ViewGraph, decimate, nearest, parse_bbox
from mapserver.bounds import MAX_QUERY_COORDINATE_M
from mapserver.errors import NotFoundError
from mapserver.store import LINK_KIND_NAMES, get_map
from mapserver.store.evidence import get_evidence

router = APIRouter(prefix="/v1/maps", tags=["viewer"])
MAX_COORDINATE = MAX_QUERY_COORDINATE_M  # metres: a query point beyond is refused (422), as is NaN or ±inf
ViewParam = Annotated[Literal["xy", "xz"], Query(description="drawing plane: xy (top view) or xz (side view)")]


def view_cache(request: Request, services: Services) -> ViewCache:
    """Return the application's viewer graph cache (created on first use, for the running database)."""
    cache: ViewCache | None = getattr(request.app.state, "view_cache", None)
    if cache is None or cache.db is not services.db:
        cache = ViewCache(services.db)
        request.app.state.view_cache = cache
    return cache


async def _graph(request: Request, services: Services, name: str) -> ViewGraph:
    cache = view_cache(request, services)
    return await run_in_threadpool(cache.get, name)


@router.get(
    "/{name}/graph", operation_id="get_graph_view",
    responses={**MAP_ERRORS, 400: {"model": ErrorPublic, "description": "bbox is not xmin,ymin,xmax,ymax"}},
)  # fmt: skip
async def read_graph(
    name: MapName,
    request: Request,
    services: ServicesDep,
    _token: ReadAccess,
    bbox: Annotated[str | None, Query(description="xmin,ymin,xmax,ymax in the drawing plane (default: all)")] = None,
    max_nodes: Annotated[int, Query(ge=1, le=MAX_NODES, description="most experiences returned")] = 20_000,
    view: ViewParam = "xy",
    resolution: Annotated[
        float, Query(ge=0, le=1e9, allow_inf_nan=False, description="finest grid cell worth drawing (m)")
    ] = 0.0,
) -> Response:
    """Return the map's experience graph inside ``bbox``, thinned on a grid to at most ``max_nodes`` nodes.

    Nodes come as parallel arrays (``id``, ``x``, ``y``, ``session`` index into ``sessions``); links as
    indexes ``a``, ``b`` into the node arrays with ``kind`` (index into ``kinds``) and ``active``.
    """
    box = parse_bbox(bbox)
    graph = await _graph(request, services, name)
    body = await run_in_threadpool(decimate, graph, bbox=box, max_nodes=max_nodes, view=view, resolution=resolution)
    return Response(to_json(body), media_type="application/json")


@router.get("/{name}/nearest", operation_id="get_nearest_experience", responses=MAP_ERRORS)
async def read_nearest(
    name: MapName,
    request: Request,
    services: ServicesDep,
    _token: ReadAccess,
    x: Annotated[float, Query(ge=-MAX_COORDINATE, le=MAX_COORDINATE, allow_inf_nan=False,
                              description="x in the drawing plane (m)")],
    y: Annotated[float, Query(ge=-MAX_COORDINATE, le=MAX_COORDINATE, allow_inf_nan=False,
                              description="y (or z in the side view) in the drawing plane (m)")],
    view: ViewParam = "xy",
) -> dict[str, Any]:
    """Return ``{"id", "distance"}`` of the experience nearest to a point of the drawing plane (404 when none)."""
    graph = await _graph(request, services, name)
    found = nearest(graph, x, y, view)
    if found is None:
        msg = f"map {name!r} has no experience"
        raise NotFoundError(msg)
    px, py = graph.plane(view)[found]
    return {"id": found, "distance": float(np.hypot(px - x, py - y))}


def node_details(graph: ViewGraph, name: str, node: int) -> dict[str, Any]:
    """Return one experience's pose, stamp, session, template and links (both directions)."""
    if not 0 <= node < graph.poses.shape[0]:
        msg = f"map {name!r} has no experience {node} (ids are 0..{graph.poses.shape[0] - 1})"
        raise NotFoundError(msg)
    x, y, z, yaw = graph.poses[node].tolist()
    touching = np.flatnonzero((graph.link_from == node) | (graph.link_to == node))
    template = int(graph.template[node])
    first_use = int(np.flatnonzero(graph.template == template)[0])
    return {
        "id": node, "x": x, "y": y, "z": z, "yaw": yaw, "stamp": float(graph.stamp[node]),
        "session": graph.session_names[int(graph.session[node])], "template": template,
        "template_new": first_use == node,
        "links": [
            {"from": int(graph.link_from[k]), "to": int(graph.link_to[k]),
             "kind": LINK_KIND_NAMES[int(graph.link_kind[k])], "active": bool(graph.link_active[k]),
             "dt": float(graph.link_dt[k]), "distance": float(graph.link_distance[k])}
            for k in touching.tolist()
        ],
    }  # fmt: skip


@router.get("/{name}/experiences/{node}", operation_id="get_experience", responses=MAP_ERRORS)
async def read_experience(
    name: MapName,
    node: Annotated[int, Path(ge=0, le=MAX_ID, description="experience id")],
    request: Request,
    services: ServicesDep,
    _token: ReadAccess,
) -> dict[str, Any]:
    """Return one experience: pose, stamp, session, template (``template_new``: first seen here) and its links."""
    graph = await _graph(request, services, name)
    return node_details(graph, name, node)


def _evidence(services: Services, name: str, node: int) -> tuple[bytes, str, float]:
    with services.db.read() as conn:
        record = get_map(conn=conn, name=name)
        found = get_evidence(conn=conn, map_id=record.id, experience=node)
    return found.data, found.media_type, found.frame_stamp


@router.get(
    "/{name}/experiences/{node}/evidence",
    operation_id="get_experience_evidence",
    responses={**MAP_ERRORS, 200: {"content": {"image/jpeg": {}}, "description": "the evidence JPEG"}},
    response_class=Response,
)
async def read_evidence(
    name: MapName,
    node: Annotated[int, Path(ge=0, le=MAX_ID, description="experience id")],
    services: ServicesDep,
    _token: ReadAccess,
) -> Response:
    """Return the camera frame stored as the experience's evidence (JPEG; 404 when it has none)."""
    data, media_type, frame_stamp = await run_in_threadpool(_evidence, services, name, node)
    return Response(data, media_type=media_type, headers={"X-Frame-Stamp": repr(frame_stamp)})

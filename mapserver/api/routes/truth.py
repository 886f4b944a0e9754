"""``GET /v1/maps/{name}/ground-truth``: the viewer's ground-truth overlay, each session's with its APE."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import Response
from pydantic_core import to_json
from starlette.concurrency import run_in_threadpool

from mapserver.api.deps import ReadAccess, ServicesDep
from mapserver.api.routes.graph import ViewParam, view_cache
from mapserver.api.routes.maps import MAP_ERRORS, MapName
from mapserver.api.services import Services
from mapserver.api.viewtruth import DEFAULT_TRUTH_POINTS, MAX_TRUTH_POINTS, TruthCache

router = APIRouter(prefix="/v1/maps", tags=["viewer"])


def truth_cache(request: Request, services: Services) -> TruthCache:
    """Return the application's ground-truth evaluation cache (created on first use, for the running database)."""
    cache: TruthCache | None = getattr(request.app.state, "truth_cache", None)
    if cache is None or cache.db is not services.db:
        cache = TruthCache(services.db)
        request.app.state.truth_cache = cache
    return cache


@router.get("/{name}/ground-truth", operation_id="get_ground_truth_overlay", responses=MAP_ERRORS)
async def read_ground_truth(
    name: MapName,
    request: Request,
    services: ServicesDep,
    _token: ReadAccess,
    view: ViewParam = "xy",
    limit: Annotated[
        int, Query(ge=2, le=MAX_TRUTH_POINTS, description="most ground-truth points returned per session")
    ] = DEFAULT_TRUTH_POINTS,
) -> Response:
    """Return each session's stored ground truth in the map's frame, with its APE as ``mapserver evaluate`` gives it.

    ``{"sessions": [{"name", "rows", "drawn", "x", "y", "ape", "error"}], "without": [names], "view"}``:
    ``x``, ``y`` are the drawing plane's coordinates of at most ``limit`` ground-truth points (evenly spread,
    first and last kept), after the session's alignment (``ape.alignment``) is undone; ``ape`` is the
    ``evaluate --session NAME`` result (None, with ``error``, when the ground truth and the experiences do not
    meet in time); ``without`` names the map's sessions that have no ground truth. A map without any gives
    ``{"sessions": [], ...}``.
    """
    graph = await run_in_threadpool(view_cache(request, services).get, name)
    body = await run_in_threadpool(truth_cache(request, services).overlay, graph, view=view, limit=limit)
    return Response(to_json(body), media_type="application/json")

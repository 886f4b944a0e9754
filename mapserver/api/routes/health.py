"""``GET /healthz``: liveness (no token needed); in distributed mode also the broker and the workers seen.

``GET /metrics``: Prometheus text format (no token needed; counts and latencies only).
"""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST
from starlette.concurrency import run_in_threadpool

from mapserver.api.metrics import render
from mapserver.api.schemas import HealthPublic

router = APIRouter(tags=["health"])


@router.get("/healthz", operation_id="get_health", response_model=HealthPublic, response_model_exclude_none=True)
async def get_health(request: Request) -> HealthPublic:
    """Return ``{"status": "ok"}`` while the server runs (plus broker and workers with Celery jobs).

    Answered on the event loop (no worker-thread hop) unless the job engine has a health check of its own
    (Celery: broker and workers, which may wait on the network), which runs in a worker thread.
    """
    services = getattr(request.app.state, "services", None)
    health = getattr(getattr(services, "jobs", None), "health", None)
    if health is None:
        return HealthPublic()
    return HealthPublic(**await run_in_threadpool(health))


@router.get("/metrics", operation_id="get_metrics", response_class=Response,
            responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}})  # fmt: skip
async def get_metrics(request: Request) -> Response:
    """Return the server's metrics in Prometheus text format (jobs, durations, frames/s, merges, path latency)."""
    body = await run_in_threadpool(render, request.app.state.services.db)
    return Response(body, media_type=CONTENT_TYPE_LATEST)

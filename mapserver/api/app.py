"""The FastAPI application factory: ``create_app(settings)`` (no work at import time)."""

from __future__ import annotations

import gc
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.routing import APIRoute
from starlette.concurrency import run_in_threadpool

from mapserver import __version__
from mapserver.api.docs import install_docs
from mapserver.api.errors import install_error_handlers
from mapserver.api.lifecycle import ServerLock
from mapserver.api.openapi import install_openapi
from mapserver.api.requestid import RequestIdMiddleware
from mapserver.api.routes import health, jobs, limits, links, maps, sessions, token
from mapserver.api.services import Services
from mapserver.api.settings import Settings
from mapserver.api.slots import ReadSlots
from mapserver.api.viewer import install_viewer
from mapserver.ingest.decode import set_max_image_pixels

DESCRIPTION = """\
Multisession RatSLAM map server. Upload mission logs (ROS 1/ROS 2 bags), follow their processing
jobs, list maps and ask for shortest paths between experiences. Writes need a bearer token with
scope `write`; reads need a `read` or `write` token unless the server allows anonymous reads.
Errors are `{"detail": "..."}`.
"""


def _operation_id(route: APIRoute) -> str:
    """Return the route's explicit operation id (every route sets one; the name is the fallback)."""
    return route.operation_id or route.name


def create_app(settings: Settings | None = None, *, server_lock: ServerLock | None = None) -> FastAPI:
    """Return the REST API application; the database and job engine start with its lifespan.

    Args:
        settings: server settings (default: :meth:`Settings.from_env`).
        server_lock: the database's server lock, already held by the caller (``mapserver serve``); without
            it the lifespan takes the lock itself when the settings need one (SQLite, embedded jobs).

    Returns:
        The application (run it with uvicorn, or wrap it in ``fastapi.testclient.TestClient``).
    """
    chosen = settings if settings is not None else Settings.from_env()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        previous_pixels = set_max_image_pixels(chosen.max_image_pixels)  # read by every job's decoder
        services = await run_in_threadpool(Services.start, chosen, server_lock)
        app.state.services = services
        # the long-lived startup objects (modules, routes, schemas) leave the collector's view: a full
        # collection then scans only what requests leave behind, not ~150k objects (tens of ms: p99, issue 6)
        gc.collect()
        gc.freeze()
        try:
            yield
        finally:
            await run_in_threadpool(services.close)
            set_max_image_pixels(previous_pixels)

    app = FastAPI(
        docs_url=None,  # served by install_docs, from this server's files
        redoc_url=None,
        title="mapserver",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
        generate_unique_id_function=_operation_id,
    )
    app.state.settings = chosen
    app.state.export_slots = ReadSlots(chosen.max_exports)
    install_error_handlers(app)
    app.add_middleware(RequestIdMiddleware)  # X-Request-ID on every response; the reference of 5xx answers
    for module in (health, sessions, jobs, maps, limits, links, token):
        app.include_router(module.router)
    install_viewer(app)  # the web viewer at / and its routes (issue 16)
    install_docs(app)  # /docs and /redoc, from this server's files
    install_openapi(app)  # errors declared as answered: {"detail": str}, 422 included
    return app

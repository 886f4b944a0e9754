"""The web viewer: static HTML/JS/CSS of the project's own (no build step, no CDN) served at ``/``.

:func:`install_viewer` adds the viewer's API routes (graph for a viewport, node details and evidence,
merge events with undo/redo) and the page itself. The page holds no data: everything it shows comes
from the REST API with the token pasted into it (kept in the browser's ``sessionStorage``), under the
API's token rules.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from mapserver.api.routes import graph, merges, truth

STATIC = Path(__file__).resolve().parent / "static"


def install_viewer(app: FastAPI) -> None:
    """Add the viewer's API routes, ``/viewer/static/*`` and the page at ``/``."""
    app.include_router(graph.router)
    app.include_router(merges.router)
    app.include_router(truth.router)  # the ground-truth overlay with each session's APE
    app.mount("/viewer/static", StaticFiles(directory=STATIC), name="viewer-static")

    @app.get("/", include_in_schema=False)
    async def viewer_page() -> FileResponse:
        """Return the viewer's page."""
        return FileResponse(STATIC / "index.html", media_type="text/html; charset=utf-8")

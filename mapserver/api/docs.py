"""``/docs`` (Swagger UI) and ``/redoc`` (ReDoc) served from this server's own files: they work offline.

The two front ends' files are those the ``fastapi-offline`` package ships (Swagger UI 5, which reads
OpenAPI 3.1, and ReDoc's standalone bundle), mounted at :data:`DOCS_STATIC`. The pages are FastAPI's own
(``get_swagger_ui_html``, ``get_redoc_html``) pointed at those files, with a Content-Security-Policy that
keeps them on this server: ReDoc's bundle would otherwise fetch its logo from its makers' CDN.
"""

from __future__ import annotations

from pathlib import Path

import fastapi_offline
from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

DOCS_STATIC = "/docs-static"
"""Where Swagger UI's and ReDoc's files are served."""

FILES = Path(fastapi_offline.__file__).resolve().parent / "static"

POLICY = (
    "default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data:; font-src 'self' data:; worker-src 'self' blob:; connect-src 'self'"
)
"""The pages' Content-Security-Policy: scripts, styles, images and requests from this server only (inline
scripts start the two front ends; ReDoc runs a search worker from a blob)."""


def install_docs(app: FastAPI) -> None:
    """Mount the front ends' files and add ``/docs``, its OAuth2 redirect and ``/redoc`` (none in the schema)."""
    app.mount(DOCS_STATIC, StaticFiles(directory=FILES), name="docs-static")
    openapi_url = app.openapi_url or "/openapi.json"
    redirect_url = app.swagger_ui_oauth2_redirect_url or "/docs/oauth2-redirect"

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        files = f"{root}{DOCS_STATIC}"
        page = get_swagger_ui_html(
            openapi_url=f"{root}{openapi_url}", title=f"{app.title} - Swagger UI",
            oauth2_redirect_url=f"{root}{redirect_url}", swagger_js_url=f"{files}/swagger-ui-bundle.js",
            swagger_css_url=f"{files}/swagger-ui.css", swagger_favicon_url=f"{files}/favicon.png",
        )  # fmt: skip
        return _kept_here(page)

    @app.get(redirect_url, include_in_schema=False)
    async def swagger_ui_redirect() -> HTMLResponse:
        return _kept_here(get_swagger_ui_oauth2_redirect_html())

    @app.get("/redoc", include_in_schema=False)
    async def redoc(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        files = f"{root}{DOCS_STATIC}"
        page = get_redoc_html(
            openapi_url=f"{root}{openapi_url}", title=f"{app.title} - ReDoc",
            redoc_js_url=f"{files}/redoc.standalone.js", redoc_favicon_url=f"{files}/favicon.png",
            with_google_fonts=False,
        )  # fmt: skip
        return _kept_here(page)


def _kept_here(page: HTMLResponse) -> HTMLResponse:
    """Return ``page`` with the Content-Security-Policy :data:`POLICY`."""
    page.headers["Content-Security-Policy"] = POLICY
    return page

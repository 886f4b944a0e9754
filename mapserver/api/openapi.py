"""The OpenAPI schema as the server answers: every error declared with the body it has.

FastAPI declares validation failures (422) as its own ``HTTPValidationError`` (an array of objects); this
server answers every error, 422 included, with ``{"detail": "..."}`` (``ErrorPublic``, see
:mod:`mapserver.api.errors`). :func:`install_openapi` makes the generated schema say so: every 4xx/5xx
response of every operation gets the ``ErrorPublic`` body, every operation declares 500 (whose body names
the request id) and every response the ``X-Request-ID`` header; FastAPI's validation schemas are dropped.
"""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from mapserver.api.requestid import REQUEST_ID_HEADER

ERROR_REF = {"$ref": "#/components/schemas/ErrorPublic"}
ERROR_BODY = {"application/json": {"schema": ERROR_REF}}
REQUEST_ID = {
    REQUEST_ID_HEADER: {
        "description": "the request's id (the client's own when it sent a valid one); 5xx bodies and the server "
        "log name it",
        "schema": {"type": "string"},
    }
}
INTERNAL = "internal error: the body names only the request id; the server log has the detail"
_FASTAPI_ERRORS = ("HTTPValidationError", "ValidationError")


def declare_errors(schema: dict[str, Any]) -> dict[str, Any]:
    """Rewrite a generated OpenAPI schema in place so that its errors are declared as answered; return it."""
    for path in schema.get("paths", {}).values():
        for operation in path.values():
            if not isinstance(operation, dict) or "responses" not in operation:
                continue
            responses: dict[str, Any] = operation["responses"]
            responses.setdefault("500", {"description": INTERNAL})
            for code, response in responses.items():
                if code.isdigit() and int(code) >= 400:
                    response["content"] = dict(ERROR_BODY)
                    if code == "422":
                        response["description"] = "a parameter or field is invalid (the detail says which)"
                response.setdefault("headers", {}).update(REQUEST_ID)
    components = schema.get("components", {}).get("schemas", {})
    for name in _FASTAPI_ERRORS:
        components.pop(name, None)
    return schema


def install_openapi(app: FastAPI) -> None:
    """Serve the schema :func:`declare_errors` rewrites (built once, on the first request for it)."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = declare_errors(
                get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
            )
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]

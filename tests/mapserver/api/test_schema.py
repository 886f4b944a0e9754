"""Property-based run of every endpoint against the OpenAPI schema (schemathesis): never a 5xx, and every
answer as the schema declares it (status code, content type, headers and body schema, errors included)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from mapserver.api import create_app
from tests.mapserver.api.conftest import api_settings, bearer, make_token
from tests.mapserver.api.graphmaps import store_graph_map

EXAMPLES = int(os.environ.get("MAPSERVER_SCHEMA_EXAMPLES", "40"))
CONFORMANCE = [not_a_server_error, status_code_conformance, content_type_conformance, response_headers_conformance,
               response_schema_conformance]  # fmt: skip


def _exercise(operation: Any, headers: dict[str, str], seen: set[int]) -> None:
    @given(case=operation.as_strategy())
    @settings(max_examples=EXAMPLES, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    def check(case: Any) -> None:
        response = case.call(headers={**(case.headers or {}), **headers})
        seen.add(response.status_code)
        assert response.status_code < 500, (case.method, case.formatted_path, response.text)
        if response.status_code >= 400:
            assert isinstance(response.json()["detail"], str)
        case.validate_response(response, checks=CONFORMANCE)

    check()


def test_no_server_errors(tmp_path: Path) -> None:
    app_settings = api_settings(tmp_path, max_upload_bytes=200_000)
    app = create_app(app_settings)
    poses = np.column_stack([np.arange(20.0), np.zeros(20), np.zeros(20), np.zeros(20)])
    store_graph_map(app_settings.db_url, "lab", poses, [(k, k + 1, 1.0, 1.0) for k in range(19)])
    headers = bearer(make_token(app_settings.db_url, "write"))
    # schemathesis runs the app's lifespan (database, job engine) once, until the test process ends: a
    # TestClient around it would start a second server on the database, which its server lock refuses
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    operations = [result.ok() for result in schema.get_all_operations()]
    # 9 (the jobs listed), session move, the viewer's 9 (graph, nearest, node, evidence, ground truth, merges x4),
    # metrics, limits, links x2, and a map's lifecycle: delete, restore, rename, and the token's scope
    assert len(operations) == 27
    statuses: dict[str, set[int]] = {}
    for operation in operations:
        _exercise(operation, headers, statuses.setdefault(operation.label, set()))
    # every operation was exercised and answered (4xx for the client's mistakes, never 5xx)
    assert all(statuses.values()), statuses
    assert any(code == 200 for code in statuses["GET /v1/maps/{name}/path"] | statuses["GET /v1/maps"])

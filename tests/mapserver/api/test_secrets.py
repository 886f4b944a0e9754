"""What answers and job records must not carry: token characters, exception text, paths, URLs, other maps.

Each must-not is paired with its must: an expired token is refused naming its id while a fresh one works;
a 500 names the request id (the same as ``X-Request-ID``) while the server log has the detail.
"""

from __future__ import annotations

import json
import logging
import subprocess
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapserver.api.requestid import internal_error_detail
from mapserver.errors import StoreError
from mapserver.store import open_database
from mapserver.store.models import ApiToken, utcnow
from mapserver.store.tokens import LAST_USED_RESOLUTION_S, create_token
from tests.mapserver.api.conftest import MAPSERVER, Api, bearer
from tests.mapserver.api.graphmaps import store_graph_map

SECRET = "postgresql+psycopg://admin:hunter2@db.internal/prod at /srv/tmp/mapserver-xyz"


def _token(api: Api, scope: str, expires_in: timedelta | None) -> tuple[str, int]:
    expires_at = None if expires_in is None else utcnow() + expires_in
    with open_database(api.db_url) as db, db.write() as conn:
        token, record = create_token(conn=conn, scope=scope, expires_at=expires_at)
    return token, record.id


def test_an_expired_token_gets_401_naming_its_id_and_a_fresh_one_works(api: Api) -> None:
    expired, expired_id = _token(api, "read", timedelta(seconds=-1))
    fresh, _ = _token(api, "read", timedelta(hours=1))
    refused = api.client.get("/v1/maps", headers=bearer(expired))
    assert refused.status_code == 401
    detail = refused.json()["detail"]
    assert detail.startswith(f"token {expired_id} expired at ")
    assert expired[:8] not in detail and expired[4:12] not in detail
    assert refused.headers["www-authenticate"] == 'Bearer error="invalid_token"'
    assert api.client.get("/v1/maps", headers=bearer(fresh)).status_code == 200


def test_the_cli_creates_an_expiring_token(api: Api) -> None:
    out = subprocess.run([MAPSERVER, "token", "create", "--db", api.db_url, "--scope", "read", "--expires", "30d",
                          "--json"], capture_output=True, text=True, check=True)  # fmt: skip
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["expires_at"] is not None
    assert api.client.get("/v1/maps", headers=bearer(result["token"])).status_code == 200
    bad = subprocess.run([MAPSERVER, "token", "create", "--db", api.db_url, "--scope", "read", "--expires", "soon"],
                         capture_output=True, text=True)  # fmt: skip
    assert bad.returncode == 2 and "duration" in bad.stderr
    listing = subprocess.run([MAPSERVER, "token", "list", "--db", api.db_url, "--json"], capture_output=True,
                             text=True, check=True)  # fmt: skip
    tokens = json.loads(listing.stdout.strip().splitlines()[-1])["tokens"]
    assert [t["expired"] for t in tokens if t["id"] == result["id"]] == [False]


def test_403_names_the_token_id_never_its_characters(api: Api, strip_log: Path) -> None:
    token, token_id = _token(api, "read", None)
    denied = api.upload(strip_log, headers=bearer(token))
    assert denied.status_code == 403
    detail = denied.json()["detail"]
    assert detail.startswith(f"token {token_id} has scope 'read'")
    assert token[:6] not in detail and token[4:12] not in detail


def test_last_used_at_is_written_at_most_once_a_minute(api: Api) -> None:
    import time

    import sqlalchemy as sa

    assert LAST_USED_RESOLUTION_S == 60.0
    token, token_id = _token(api, "read", None)

    def last_used() -> Any:
        with open_database(api.db_url) as db, db.read() as conn:
            return conn.execute(sa.select(ApiToken.last_used_at).where(ApiToken.id == token_id)).scalar_one()

    assert api.client.get("/v1/maps", headers=bearer(token)).status_code == 200
    deadline = time.monotonic() + 10
    while last_used() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    first = last_used()
    assert first is not None
    for _ in range(5):
        assert api.client.get("/v1/maps", headers=bearer(token)).status_code == 200
    time.sleep(0.3)
    assert last_used() == first  # within the minute: not written again


def test_a_500_names_the_request_id_and_the_log_has_the_detail(
    api: Api, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    import mapserver.api.routes.maps as maps_route

    def broken(**_: Any) -> Any:
        raise StoreError(f"database error on {SECRET}")

    monkeypatch.setattr(maps_route, "list_maps", broken)
    with caplog.at_level(logging.ERROR):
        response = api.client.get("/v1/maps", headers=api.read)
    assert response.status_code == 500
    request_id = response.headers["x-request-id"]
    assert response.json() == {"detail": internal_error_detail(request_id)}
    assert "hunter2" not in response.text and "/srv/tmp" not in response.text and "StoreError" not in response.text
    assert any(request_id in r.getMessage() and "hunter2" in r.getMessage() for r in caplog.records)

    def crash(**_: Any) -> Any:
        raise RuntimeError(SECRET)

    monkeypatch.setattr(maps_route, "list_maps", crash)
    given = api.client.get("/v1/maps", headers={**api.read, "X-Request-ID": "trace-42"})
    assert given.status_code == 500 and given.headers["x-request-id"] == "trace-42"
    assert given.json() == {"detail": internal_error_detail("trace-42")}
    # a client's id that is not 1-64 safe characters is replaced; every answer carries one
    ok = api.client.get("/healthz", headers={"X-Request-ID": "x" * 65})
    assert ok.status_code == 200 and len(ok.headers["x-request-id"]) == 16


def test_a_5xx_http_exception_names_the_request_id_and_a_4xx_keeps_its_detail(
    api: Api, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    from starlette.exceptions import HTTPException

    import mapserver.api.routes.maps as maps_route

    def upstream(**_: Any) -> Any:
        raise HTTPException(status_code=502, detail=f"bad gateway to {SECRET}")

    monkeypatch.setattr(maps_route, "list_maps", upstream)
    with caplog.at_level(logging.ERROR):
        response = api.client.get("/v1/maps", headers=api.read)
    request_id = response.headers["x-request-id"]
    assert response.status_code == 500 and response.json() == {"detail": internal_error_detail(request_id)}
    assert "hunter2" not in response.text and "/srv/tmp" not in response.text
    assert any(request_id in r.getMessage() and "hunter2" in r.getMessage() for r in caplog.records)
    missing = api.client.get("/v1/no-such-route", headers=api.read)
    assert missing.status_code == 404 and missing.json() == {"detail": "Not Found"}


def test_the_health_reports_an_unreachable_broker_without_its_url() -> None:
    from mapserver.api.cluster import broker_problem

    refused = OSError("Error 111 connecting to redis://admin:hunter2@mq.internal:6379/0.\nConnection refused.")
    assert broker_problem(refused) == "unreachable: Error 111 connecting to <broker> Connection refused."
    assert broker_problem(OSError("timed out")) == "unreachable: timed out"


@pytest.mark.parametrize("error", [StoreError, RuntimeError])
def test_a_job_record_names_the_uploads_request_id_not_the_error(
    api: Api, strip_log: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, error: type[Exception]
) -> None:
    from mapserver.processing import pipeline

    def broken(*_: Any, **__: Any) -> Any:
        raise error(f"database error on {SECRET}")

    monkeypatch.setattr(pipeline, "process_into_store", broken)
    upload = api.upload(strip_log, preset="irat")
    assert upload.status_code == 202
    job = api.wait(upload.json()["job"])
    assert job["status"] == "failed"
    assert job["error"] == internal_error_detail(upload.headers["x-request-id"])
    assert "hunter2" not in json.dumps(job) and "/srv/tmp" not in json.dumps(job)
    logged = [r.getMessage() for r in caplog.records if upload.headers["x-request-id"] in r.getMessage()]
    assert any("hunter2" in line for line in logged)  # the detail went to the log under the same reference


def test_a_job_refused_for_its_parameters_shows_the_message(
    api: Api, strip_log: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The engine's ConfigError is the client's input: the job record shows its message, not an internal error."""
    from core.config import ConfigError
    from mapserver.processing import pipeline

    def refused(*_: Any, **__: Any) -> Any:
        raise ConfigError("parameter 'frontend_backbone' = 'vgg': must be one of none, shufflenetv2, alexnet")

    monkeypatch.setattr(pipeline, "process_into_store", refused)
    upload = api.upload(strip_log, preset="irat")
    job = api.wait(upload.json()["job"])
    assert job["status"] == "failed"
    assert job["error"] == "parameter 'frontend_backbone' = 'vgg': must be one of none, shufflenetv2, alexnet"


def test_a_404_for_an_unknown_map_lists_no_other_map(api: Api) -> None:
    store_graph_map(api.db_url, "classified-site", np.zeros((2, 4)), [(0, 1, 1.0, 1.0)])
    response = api.client.get("/v1/maps/nope", headers=api.read)
    assert response.status_code == 404
    assert response.json()["detail"] == "no map named 'nope' in this database"
    assert api.client.get("/v1/maps/classified-site", headers=api.read).status_code == 200

"""Every auth case: no token, malformed, unknown, revoked, read token on a write, anonymous reads."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from mapserver.store import open_database
from mapserver.store.models import ApiToken
from mapserver.store.tokens import authenticate_token, create_token, hash_token, revoke_token
from tests.mapserver.api.conftest import Api, bearer

READS = ["/v1/maps", "/v1/maps/x", "/v1/maps/x/experiences", "/v1/maps/x/path?from=0&to=1",
         "/v1/maps/x/export", "/v1/jobs/1"]  # fmt: skip


def _assert_401(response: Any, detail_part: str, invalid: bool) -> None:
    assert response.status_code == 401, response.text
    assert detail_part in response.json()["detail"]
    expected = 'Bearer error="invalid_token"' if invalid else "Bearer"
    assert response.headers["www-authenticate"] == expected


@pytest.mark.parametrize("path", READS)
def test_reads_need_a_token(api: Api, path: str) -> None:
    _assert_401(api.client.get(path), "needs a token", invalid=False)
    _assert_401(api.client.get(path, headers=bearer("msk_not-a-real-token")), "unknown token", invalid=True)
    _assert_401(api.client.get(path, headers={"Authorization": "Basic dXNlcjpwdw=="}), "Bearer <token>", True)
    expected = 200 if path == "/v1/maps" else 404  # authorised: the map / job does not exist
    assert api.client.get(path, headers=api.read).status_code == expected
    assert api.client.get(path, headers=api.write).status_code == expected


def test_writes_need_a_write_token(api: Api, strip_log: Path) -> None:
    _assert_401(api.upload(strip_log, headers={}), "scope 'write'", invalid=False)
    _assert_401(api.upload(strip_log, headers=bearer("msk_bogus")), "unknown token", invalid=True)
    denied = api.upload(strip_log, headers=api.read)
    assert denied.status_code == 403
    assert "has scope 'read'" in denied.json()["detail"]
    assert api.upload(strip_log, preset="irat").status_code == 202
    assert not any((api.settings.uploads / ".incoming").iterdir())  # refused bodies were never stored


def test_revoked_token_is_refused(api: Api) -> None:
    with open_database(api.db_url) as db, db.write() as conn:
        token, record = create_token(conn=conn, scope="read")
    assert api.client.get("/v1/maps", headers=bearer(token)).status_code == 200
    with open_database(api.db_url) as db, db.write() as conn:
        revoke_token(conn=conn, token_id=record.id)
    _assert_401(api.client.get("/v1/maps", headers=bearer(token)), f"token {record.id} was revoked", invalid=True)


def test_anonymous_reads(make_api: Any, strip_log: Path) -> None:
    api = make_api(allow_anonymous_reads=True)
    assert api.client.get("/v1/maps").json() == {"maps": []}
    # a token that is sent must still be valid, and writes still need one
    _assert_401(api.client.get("/v1/maps", headers=bearer("msk_wrong")), "unknown token", invalid=True)
    _assert_401(api.upload(strip_log, headers={}), "scope 'write'", invalid=False)
    assert api.upload(strip_log, headers=api.read).status_code == 403


def test_tokens_are_stored_hashed(api: Api) -> None:
    import sqlalchemy as sa

    with open_database(api.db_url) as db, db.write() as conn:
        token, record = create_token(conn=conn, scope="write", label="robot-1")
        stored = conn.execute(sa.select(ApiToken.token_sha256, ApiToken.prefix).where(ApiToken.id == record.id)).one()
        found = authenticate_token(conn=conn, token=token)
        assert authenticate_token(conn=conn, token=token + "x") is None
        assert authenticate_token(conn=conn, token="x" * 1000) is None
    assert stored[0] == hash_token(token) != token
    assert token not in stored[0] and stored[1] == token[:12]
    assert len(token) >= 40  # 32 random bytes, URL-safe base64, plus the prefix
    assert found is not None and found.record.scope == "write"


def test_token_cli_creates_a_usable_token(api: Api) -> None:
    import json
    import subprocess

    from tests.mapserver.api.conftest import MAPSERVER

    out = subprocess.run([MAPSERVER, "token", "create", "--db", api.db_url, "--scope", "read", "--json"],
                         capture_output=True, text=True, check=True)  # fmt: skip
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["scope"] == "read"
    assert api.client.get("/v1/maps", headers=bearer(result["token"])).status_code == 200
    assert api.upload(Path(__file__), headers=bearer(result["token"])).status_code == 403
    bad = subprocess.run([MAPSERVER, "token", "create", "--db", api.db_url, "--scope", "admin"],
                         capture_output=True, text=True)  # fmt: skip
    assert bad.returncode == 2

"""A map's lifecycle over REST (issue 65): delete (archive), restore, purge, rename, and uploads ``into`` a map.

Every refusal is paired with what must still happen. Each test runs on SQLite and on PostgreSQL.
"""

from __future__ import annotations

import hashlib
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapserver.store import NewSession, open_database, save_map
from mapserver.store.jobs import count_jobs
from tests.mapserver.api.conftest import Api
from tests.mapserver.api.logs import write_strip_log
from tests.mapserver.api.test_admission import backend_api  # noqa: F401 (the fixture)
from tests.mapserver.store.conftest import drive_engine, small_params


@cache
def _snapshot(seed: int) -> dict[str, np.ndarray]:
    return drive_engine(small_params(), laps=0.4, seed=seed).snapshot()


def _store(db_url: str, name: str, seed: int) -> None:
    """Store a small map ``name`` (one session, the strip world driven 0.4 laps) straight into the database."""
    params = small_params()
    session = NewSession(name=f"{name}-s", log_name=f"{name}.bag", log_sha256=name.ljust(64, "0"),
                         topics={"image": "/camera"}, params=params.to_dict())  # fmt: skip
    with open_database(db_url) as db:
        save_map(db, name=name, params=params, snapshot=_snapshot(seed), sessions=[session])


def _content(api: Api, name: str) -> tuple[int, str]:
    """The status of ``GET /v1/maps/{name}`` and a SHA-256 of the map (JSON and TUM exports, its details)."""
    h = hashlib.sha256()
    detail = api.client.get(f"/v1/maps/{name}", headers=api.read)
    for fmt in ("json", "tum"):
        response = api.client.get(f"/v1/maps/{name}/export?format={fmt}", headers=api.read)
        if response.status_code != 200:
            return response.status_code, ""
        h.update(response.content)
    body = detail.json()
    h.update(repr([body[k] for k in ("version", "templates", "experiences", "links", "sessions", "merge_events")])
             .encode())  # fmt: skip
    return detail.status_code, h.hexdigest()


def _names(api: Api, archived: bool = False) -> list[str]:
    query = "?archived=true" if archived else ""
    return [m["name"] for m in api.client.get(f"/v1/maps{query}", headers=api.read).json()["maps"]]


def test_delete_needs_a_write_token_and_restore_gives_the_same_map(backend_api: Api) -> None:  # noqa: F811
    api = backend_api
    _store(api.db_url, "lab", 3)
    _store(api.db_url, "yard", 5)
    before, other = _content(api, "lab"), _content(api, "yard")
    assert before[0] == 200
    # must not happen: a delete without a token, or with a read token
    assert api.client.delete("/v1/maps/lab").status_code == 401
    refused = api.client.delete("/v1/maps/lab", headers=api.read)
    assert refused.status_code == 403 and "needs scope 'write'" in refused.json()["detail"]
    assert api.client.post("/v1/maps/lab/restore", headers=api.read).status_code == 403
    assert _content(api, "lab") == before and _names(api) == ["lab", "yard"]
    # a write token deletes: the map is archived, hidden, and listed among the archived maps
    deleted = api.client.delete("/v1/maps/lab", headers=api.write)
    assert deleted.status_code == 200, deleted.text
    assert deleted.json()["map"] == "lab" and deleted.json()["status"] == "archived"
    assert _content(api, "lab")[0] == 404
    assert api.client.get("/v1/maps/lab/graph", headers=api.read).status_code == 404
    assert api.client.get("/v1/maps/lab/path?from=0&to=1", headers=api.read).status_code == 404
    assert _names(api) == ["yard"] and _names(api, archived=True) == ["lab"]
    assert api.client.get("/v1/maps?archived=true", headers=api.read).json()["maps"][0]["archived_at"]
    assert _content(api, "yard") == other  # must still happen: the other map untouched
    again = api.client.delete("/v1/maps/lab", headers=api.write)
    assert again.status_code == 409 and "archived already" in again.json()["detail"]
    assert api.client.post("/v1/maps/yard/restore", headers=api.write).status_code == 409
    assert api.client.post("/v1/maps/nope/restore", headers=api.write).status_code == 404
    # restore: the same map, bit for bit
    restored = api.client.post("/v1/maps/lab/restore", headers=api.write)
    assert restored.status_code == 200 and restored.json()["status"] == "live"
    assert _content(api, "lab") == before and _names(api) == ["lab", "yard"]


def test_purge_takes_an_archived_map_only(backend_api: Api) -> None:  # noqa: F811
    api = backend_api
    _store(api.db_url, "lab", 3)
    before = _content(api, "lab")
    live = api.client.delete("/v1/maps/lab?purge=true", headers=api.write)
    assert live.status_code == 409 and "delete it first" in live.json()["detail"]
    assert _content(api, "lab") == before
    assert api.client.delete("/v1/maps/lab", headers=api.write).status_code == 200
    assert api.client.delete("/v1/maps/lab?purge=true", headers=api.read).status_code == 403
    assert _names(api, archived=True) == ["lab"]
    purged = api.client.delete("/v1/maps/lab?purge=true", headers=api.write)
    assert purged.status_code == 200, purged.text
    assert (purged.json()["status"], purged.json()["sessions"], purged.json()["merge_events"]) == ("purged", 1, 0)
    assert _names(api) == [] and _names(api, archived=True) == []
    assert api.client.post("/v1/maps/lab/restore", headers=api.write).status_code == 404


def test_rename_then_the_old_name_is_404_and_the_new_name_has_the_same_content(backend_api: Api) -> None:  # noqa: F811
    api = backend_api
    _store(api.db_url, "lab", 3)
    _store(api.db_url, "yard", 5)
    tum = api.client.get("/v1/maps/lab/export?format=tum", headers=api.read).content
    assert api.client.patch("/v1/maps/lab", json={"name": "lab2"}).status_code == 401
    assert api.client.patch("/v1/maps/lab", json={"name": "lab2"}, headers=api.read).status_code == 403
    bad = api.client.patch("/v1/maps/lab", json={"name": "a/b"}, headers=api.write)
    assert bad.status_code == 400 and "invalid map name" in bad.json()["detail"]
    taken = api.client.patch("/v1/maps/lab", json={"name": "yard"}, headers=api.write)
    assert taken.status_code == 409 and "held by another map" in taken.json()["detail"]
    assert _names(api) == ["lab", "yard"]
    renamed = api.client.patch("/v1/maps/lab", json={"name": "lab2"}, headers=api.write)
    assert renamed.status_code == 200 and renamed.json() == {
        "map": "lab2", "status": "live", "archived_at": None, "previous": "lab", "sessions": None,
        "merge_events": None}  # fmt: skip
    assert api.client.get("/v1/maps/lab", headers=api.read).status_code == 404
    assert api.client.get("/v1/maps/lab2/export?format=tum", headers=api.read).content == tum
    assert _names(api) == ["lab2", "yard"]


def test_the_token_endpoint_tells_the_viewer_what_it_may_do(api: Api) -> None:
    assert api.client.get("/v1/token").status_code == 401
    assert api.client.get("/v1/token", headers=api.write).json()["scope"] == "write"
    assert api.client.get("/v1/token", headers=api.read).json()["scope"] == "read"


def test_a_log_named_like_an_archived_map_gets_a_name_of_its_own(api: Api, tmp_path: Path) -> None:
    _store(api.db_url, "walk", 3)
    assert api.client.delete("/v1/maps/walk", headers=api.write).status_code == 200
    log = write_strip_log(tmp_path / "logs" / "walk.bag", laps=0.4, seed=4)
    job = api.wait(api.upload(log, preset="irat", merge="false").json()["job"])
    assert job["status"] == "done" and job["map"] == "walk-2", job
    assert _names(api) == ["walk-2"] and _names(api, archived=True) == ["walk"]


# --------------------------------------------------------------------------------------- upload into
def _jobs(api: Api) -> int:
    with open_database(api.db_url) as db, db.read() as conn:
        return sum(count_jobs(conn=conn).values())


def _kept_uploads(api: Api) -> list[Path]:
    root = api.settings.uploads
    return [p for p in root.iterdir() if not p.name.startswith(".")] if root.exists() else []


def test_uploads_into_a_map_are_refused_before_202_for_every_reason_known(
    backend_api: Api,  # noqa: F811
    tmp_path: Path,
) -> None:
    api = backend_api
    _store(api.db_url, "lab", 3)
    _store(api.db_url, "old", 5)
    assert api.client.delete("/v1/maps/old", headers=api.write).status_code == 200
    log = write_strip_log(tmp_path / "logs" / "walk.bag", laps=0.4, seed=4)
    refusals: list[tuple[dict[str, str], int, str]] = [
        ({"into": "nowhere"}, 404, "no map named 'nowhere' to merge into"),
        ({"into": "old"}, 409, "map 'old' is archived"),
        ({"into": "lab", "map": "new"}, 400, "give either map"),
        ({"into": "lab", "merge": "false"}, 400, "cannot be combined with merge=false"),
        ({"into": "a/b"}, 400, "invalid map name 'a/b'"),
        ({"into": "lab", "preset": "circle"}, 409, "map 'lab' cannot take this session"),
        ({"map": "old"}, 409, "held by an archived (deleted) map"),
    ]
    for fields, status, message in refusals:
        response = api.upload(log, **{"preset": "irat", **fields})
        assert response.status_code == status, (fields, response.text)
        detail = response.json()["detail"]
        assert message in detail and "--" not in detail, (fields, detail)
    assert _jobs(api) == 0 and _kept_uploads(api) == []  # nothing stored
    api.client.app.state.services.jobs.stop()  # type: ignore[attr-defined]  # the job stays queued
    accepted = api.upload(log, preset="irat", into="lab")  # must still happen
    assert accepted.status_code == 202, accepted.text
    assert accepted.json()["map"] == "lab" and _jobs(api) == 1
    busy = api.client.delete("/v1/maps/lab", headers=api.write)  # a map a pending job goes into stays
    assert busy.status_code == 409 and f"job {accepted.json()['job']}" in busy.json()["detail"]


@pytest.mark.slow
def test_an_upload_into_a_map_merges_into_it_or_fails_storing_nothing(backend_api: Api, tmp_path: Path) -> None:  # noqa: F811
    api = backend_api
    morning = write_strip_log(tmp_path / "logs" / "morning.bag", laps=1.3)
    evening = write_strip_log(tmp_path / "logs" / "evening.bag", laps=1.6, t0_ns=1_800_000_000_000_000_000)
    elsewhere = write_strip_log(tmp_path / "logs" / "elsewhere.bag", laps=1.3, seed=8)
    first = api.upload(morning, preset="irat", merge="false").json()["job"]
    assert api.wait(first, timeout=180)["status"] == "done"
    before = _content(api, "morning")
    # views of another place: the job fails in words of the API, and nothing is stored
    stranger = api.upload(elsewhere, preset="irat", into="morning")
    assert stranger.status_code == 202, stranger.text
    failed = api.wait(stranger.json()["job"], timeout=180)
    assert failed["status"] == "failed" and "did not merge into map 'morning'" in failed["error"]
    assert "--" not in failed["error"] and "nothing was stored" in failed["error"]
    assert _names(api) == ["morning"] and _content(api, "morning") == before
    # the same place: merged into the map named
    accepted = api.upload(evening, preset="irat", into="morning")
    assert accepted.status_code == 202 and accepted.json()["map"] == "morning"
    done = api.wait(accepted.json()["job"], timeout=180)
    assert done["status"] == "done" and done["map"] == "morning", done
    detail: dict[str, Any] = api.client.get("/v1/maps/morning", headers=api.read).json()
    assert sorted(s["name"] for s in detail["sessions"]) == ["evening", "morning"]
    assert [(e["mode"], e["status"]) for e in detail["merge_events"]] == [("online", "applied")]
    assert _names(api) == ["morning"]
    # a rename between an undo and a redo: the merge history follows the map to its new name
    event = detail["merge_events"][0]["id"]
    undone = api.client.post(f"/v1/merges/{event}/undo", headers=api.write)
    assert undone.status_code == 200 and sorted(undone.json()["maps"]) == ["evening", "morning"]
    assert api.client.patch("/v1/maps/morning", json={"name": "dawn"}, headers=api.write).status_code == 200
    redone = api.client.post(f"/v1/merges/{event}/redo", headers=api.write)
    assert redone.status_code == 200, redone.text
    assert redone.json()["maps"] == ["dawn"] and _names(api) == ["dawn"]

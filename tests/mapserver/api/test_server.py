"""A real ``mapserver serve`` process: concurrent uploads, and a server killed in the middle of a job."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import sqlalchemy as sa

from mapserver.params import resolve_params
from mapserver.processing import pipeline
from mapserver.store import open_database
from mapserver.store.models import Base
from tests.mapserver.api.conftest import Server, bearer, make_token, wait_job
from tests.mapserver.api.logs import write_strip_log

pytestmark = pytest.mark.slow


def _counts(db_url: str) -> dict[str, int]:
    with open_database(db_url) as db, db.read() as conn:
        return {name: int(conn.execute(sa.select(sa.func.count()).select_from(t)).scalar_one())
                for name, t in Base.metadata.tables.items()}  # fmt: skip


def _upload(url: str, token: str, path: Path, **fields: str) -> dict[str, Any]:
    with path.open("rb") as handle:
        response = httpx.post(f"{url}/v1/sessions", files={"file": (path.name, handle)}, data=fields,
                              headers=bearer(token), timeout=60)  # fmt: skip
    assert response.status_code == 202, response.text
    return response.json()


def test_concurrent_uploads_are_all_stored(server: Server, tmp_path: Path) -> None:
    server.start()
    token = make_token(server.db_url, "write")
    # two missions over the same place (same texture, different start time and length)
    logs = [write_strip_log(tmp_path / "logs" / "morning.bag", laps=1.3),
            write_strip_log(tmp_path / "logs" / "evening.bag", laps=1.6, t0_ns=1_800_000_000_000_000_000)]  # fmt: skip
    with ThreadPoolExecutor(2) as pool:
        accepted = list(pool.map(lambda p: _upload(server.url, token, p, preset="irat"), logs))
    with httpx.Client(base_url=server.url) as client:
        jobs = [wait_job(client, a["job"], bearer(token), timeout=120) for a in accepted]
        assert [j["status"] for j in jobs] == ["done", "done"], jobs
        maps = client.get("/v1/maps", headers=bearer(token)).json()["maps"]
        details = [client.get(f"/v1/maps/{m['name']}", headers=bearer(token)).json() for m in maps]
    # Both jobs ran in parallel (different maps); the one that finished second saw the other's new map,
    # processed its log again and merged: one map holding both sessions, nothing lost.
    assert [(m["name"] in ("morning", "evening"), m["sessions"]) for m in maps] == [(True, 2)]
    (detail,) = details
    assert sorted(s["name"] for s in detail["sessions"]) == ["evening", "morning"]
    assert [(e["mode"], e["status"]) for e in detail["merge_events"]] == [("online", "applied")]
    alone = {p.stem: pipeline.process_log(p, resolve_params("irat")) for p in logs}
    assert maps[0]["experiences"] >= max(r.experiences for r in alone.values())


def test_server_killed_during_a_job_reruns_it(server: Server, tmp_path: Path) -> None:
    server.start()
    token = make_token(server.db_url, "write")
    log = write_strip_log(tmp_path / "logs" / "long.bag", laps=30.0)
    job = _upload(server.url, token, log, preset="irat", map="long")["job"]
    deadline = time.monotonic() + 60
    state: dict[str, Any] = {}
    while time.monotonic() < deadline:
        state = httpx.get(f"{server.url}/v1/jobs/{job}", headers=bearer(token)).json()
        if state["status"] == "running" and state["progress"] > 0.05:
            break
        time.sleep(0.05)
    assert state["status"] == "running" and state["progress"] < 1.0, state
    server.kill()

    counts = _counts(server.db_url)  # nothing of the session was written: no half-stored map
    assert (counts["maps"], counts["sessions"], counts["experiences"], counts["templates"]) == (0, 0, 0, 0)
    with open_database(server.db_url) as db, db.read() as conn:
        from mapserver.store.jobs import get_job

        assert get_job(conn=conn, job_id=job).status == "running"

    server.start()
    with httpx.Client(base_url=server.url) as client:
        done = wait_job(client, job, bearer(token), timeout=180)
        assert done["status"] == "done", done
        assert done["map"] == "long" and done["session"] == "long"
        maps = client.get("/v1/maps", headers=bearer(token)).json()["maps"]
    expected = pipeline.process_log(log, resolve_params("irat"))
    health = maps[0].pop("health")
    assert maps == [{"name": "long", "sessions": 1, "templates": expected.templates,
                     "experiences": expected.experiences, "links": expected.links,
                     "merges": {"applied": 0, "undone": 0, "rejected": 0, "unverified": 0}}]  # fmt: skip
    # the resumed job switched off what an uninterrupted run switches off (30 laps: one link 24 → 26)
    off = int(np.count_nonzero(~expected.engine.map.link_active))
    assert health["switched_off"] == off and health["links"] == expected.links
    with open_database(server.db_url) as db, db.read() as conn:
        from mapserver.store.jobs import get_job

        assert (get_job(conn=conn, job_id=job).options or {})["attempts"] == 1

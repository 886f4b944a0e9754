"""``GET /v1/jobs``: every job, newest first, a page at a time, filtered by status and map."""

from __future__ import annotations

from typing import Any

from sqlalchemy import update

from mapserver.store import open_database
from mapserver.store.jobs import create_job
from mapserver.store.models import Job
from tests.mapserver.api.conftest import Api

STATUSES = ["done", "failed", "done", "failed", "done", "done", "done"]
MAPS = ["a", "a", "a", "a", "b", "b", "b"]


def _stored_jobs(db_url: str) -> list[int]:
    """Store seven finished jobs (statuses and map names above) in one transaction, so no worker claims one."""
    with open_database(db_url) as db, db.write() as conn:
        ids = []
        for status, name in zip(STATUSES, MAPS, strict=True):
            job = create_job(conn=conn, upload_path=f"/nowhere/{len(ids)}.bag", upload_name=f"{len(ids)}.bag",
                             map_name=name)  # fmt: skip
            conn.execute(update(Job).where(Job.id == job.id).values(status=status, error="bad log" if status == "failed"
                                                                   else None))  # fmt: skip
            ids.append(job.id)
    return ids


def _ids(body: dict[str, Any]) -> list[int]:
    return [job["job"] for job in body["jobs"]]


def test_pages_run_newest_first_and_end(api: Api) -> None:
    ids = _stored_jobs(api.db_url)
    first = api.client.get("/v1/jobs", params={"limit": 3}, headers=api.read).json()
    assert _ids(first) == ids[::-1][:3] and first["total"] == 7 and first["next"] == ids[4]
    second = api.client.get("/v1/jobs", params={"limit": 3, "before": first["next"]}, headers=api.read).json()
    assert _ids(second) == ids[::-1][3:6] and second["next"] == ids[1]
    last = api.client.get("/v1/jobs", params={"limit": 3, "before": second["next"]}, headers=api.read).json()
    assert _ids(last) == [ids[0]] and last["next"] is None  # must: the last page says so
    exact = api.client.get("/v1/jobs", params={"limit": 7}, headers=api.read).json()
    assert len(exact["jobs"]) == 7 and exact["next"] is None  # must not: a next page that would be empty
    assert first["jobs"][0]["upload"] == "6.bag" and first["jobs"][0]["map"] == "b"


def test_filters_by_status_and_map(api: Api) -> None:
    ids = _stored_jobs(api.db_url)
    get = lambda **params: api.client.get("/v1/jobs", params=params, headers=api.read).json()  # noqa: E731
    failed = get(status="failed")
    assert _ids(failed) == [ids[3], ids[1]] and failed["total"] == 2
    assert all(job["error"] == "bad log" for job in failed["jobs"])
    assert _ids(get(map="a")) == ids[3::-1] and get(map="a")["total"] == 4
    assert _ids(get(map="b", status="done")) == ids[:3:-1]
    assert get(map="nowhere") == {"jobs": [], "total": 0, "next": None}
    assert get(status="queued")["total"] == 0


def test_bad_queries_and_missing_tokens_are_refused(api: Api) -> None:
    _stored_jobs(api.db_url)
    for params in ({"status": "lost"}, {"limit": 0}, {"limit": 101}, {"before": 0}, {"map": ""}):
        response = api.client.get("/v1/jobs", params=params, headers=api.read)
        assert response.status_code == 422 and isinstance(response.json()["detail"], str), params
    assert api.client.get("/v1/jobs").status_code == 401
    assert api.client.get("/v1/jobs", params={"limit": 100}, headers=api.read).status_code == 200

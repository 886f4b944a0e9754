"""The Celery engine on real PostgreSQL and Redis, with worker and API processes started here (issue 15)."""

from __future__ import annotations

import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import sqlalchemy as sa

from mapserver.params import resolve_params
from mapserver.processing import pipeline
from mapserver.store import open_database
from mapserver.store.models import Job, Session
from tests.mapserver.api.cluster import RABBITMQ, Cluster, local_cluster
from tests.mapserver.api.conftest import Api
from tests.mapserver.api.logs import write_strip_log

pytestmark = [pytest.mark.postgres, pytest.mark.slow]

LATER_NS = 1_800_000_000_000_000_000


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    with local_cluster(tmp_path) as made:
        yield made


def _world_logs(tmp_path: Path) -> list[Path]:
    """Two missions (different start time and length) over each of three worlds; both named after the world."""
    logs = []
    for k, seed in enumerate((3, 11, 19)):
        logs.append(write_strip_log(tmp_path / "logs" / f"first-{k}" / f"w{seed}.bag", seed=seed, laps=1.3))
    for k, seed in enumerate((3, 11, 19)):
        logs.append(write_strip_log(tmp_path / "logs" / f"second-{k}" / f"w{seed}.bag", seed=seed, laps=1.5,
                                    t0_ns=LATER_NS))  # fmt: skip
    return logs


def _maps_and_merges(get: Any) -> list[tuple[Any, ...]]:
    maps = get("/v1/maps")["maps"]
    out = []
    for m in maps:
        detail = get(f"/v1/maps/{m['name']}")
        out.append((m["name"], m["sessions"], m["templates"], m["experiences"], m["links"],
                    len(detail["merge_events"])))  # fmt: skip
    return sorted(out)


def _rows(db_url: str, *columns: Any) -> list[Any]:
    with open_database(db_url) as db, db.read() as conn:
        return list(conn.execute(sa.select(*columns).order_by(columns[0])).all())


def test_six_uploads_over_three_maps_on_two_workers(cluster: Cluster, make_api: Any, tmp_path: Path) -> None:
    cluster.start_worker("w1")
    cluster.start_worker("w2")
    cluster.start_api("api")
    cluster.wait_api("api")
    health = cluster.wait_workers("api", ["w1", "w2"])
    assert (health["status"], health["engine"], health["broker"]) == ("ok", "celery", "ok")

    logs = _world_logs(tmp_path)
    accepted = [cluster.upload("api", log, preset="irat") for log in logs]
    jobs = [a["job"] for a in accepted]
    states = cluster.wait_jobs("api", jobs)
    assert [s["status"] for s in states] == ["done"] * 6, states
    assert len({s["session"] for s in states}) == 6
    # each job ran once, on one of the two workers, and both workers took part (maps run in parallel)
    rows = _rows(cluster.db_url, Job.id, Job.lease_owner, Job.options)
    assert [r.options["attempts"] for r in rows] == [0] * 6
    assert {r.lease_owner.split(":")[0] for r in rows} == {cluster.worker_name("w1"), cluster.worker_name("w2")}
    assert len(_rows(cluster.db_url, Session.id)) == 6
    clustered = _maps_and_merges(lambda p: cluster.get("api", p))

    # the same uploads through the embedded engine (SQLite, threads): the same maps and merges
    api: Api = make_api()
    embedded_jobs = [api.upload(log, preset="irat").json()["job"] for log in logs]
    assert [api.wait(j, timeout=120)["status"] for j in embedded_jobs] == ["done"] * 6
    embedded = _maps_and_merges(lambda p: api.client.get(p, headers=api.read).json())
    assert clustered == embedded
    assert [(m[0], m[1], m[5]) for m in clustered] == [("w11", 2, 1), ("w19", 2, 1), ("w3", 2, 1)]

    metrics = httpx.get(cluster.url("api") + "/metrics", timeout=30).text
    assert 'mapserver_jobs{status="done"} 6.0' in metrics
    assert 'mapserver_jobs{status="queued"} 0.0' in metrics
    assert 'mapserver_merge_events{status="applied"} 3.0' in metrics
    assert "mapserver_job_duration_seconds_count 6.0" in metrics
    assert f"mapserver_job_frames_total {float(sum(a['frames'] for a in accepted))}" in metrics


def test_a_worker_killed_mid_job_is_replaced_and_the_job_stored_once(cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("w1")
    cluster.start_worker("w2")
    cluster.start_api("api")
    cluster.wait_api("api")
    cluster.wait_workers("api", ["w1", "w2"])
    log = write_strip_log(tmp_path / "logs" / "long.bag", laps=40.0)
    job = cluster.upload("api", log, preset="irat")["job"]
    deadline = time.monotonic() + 60
    state: dict[str, Any] = {}
    while time.monotonic() < deadline:
        state = cluster.job("api", job)
        if state["status"] == "running" and state["progress"] > 0.05:
            break
        time.sleep(0.05)
    assert state["status"] == "running" and state["progress"] < 0.9, state
    (owner,) = [r.lease_owner for r in _rows(cluster.db_url, Job.id, Job.lease_owner)]
    victim, survivor = ("w1", "w2") if owner.startswith(cluster.worker_name("w1")) else ("w2", "w1")
    cluster.signal(victim, signal.SIGKILL)  # the worker and its pool process, mid-job

    (done,) = cluster.wait_jobs("api", [job], timeout=90)
    assert done["status"] == "done", (done, cluster.log(survivor))
    (row,) = _rows(cluster.db_url, Job.id, Job.lease_owner, Job.options)
    assert row.lease_owner.startswith(cluster.worker_name(survivor))
    assert row.options["attempts"] == 1  # taken over once
    assert len(_rows(cluster.db_url, Session.id)) == 1
    expected = pipeline.process_log(log, resolve_params("irat"))  # an intact map: the same as one clean run
    (listed,) = cluster.get("api", "/v1/maps")["maps"]
    listed.pop("health")
    assert listed == {"name": "long", "sessions": 1, "templates": expected.templates,
                      "experiences": expected.experiences, "links": expected.links,
                     "merges": {"applied": 0, "undone": 0, "rejected": 0, "unverified": 0}}  # fmt: skip


def test_two_api_replicas_share_the_queue_and_a_restart_loses_nothing(cluster: Cluster, tmp_path: Path) -> None:
    cluster.start_worker("w1", concurrency=2)
    cluster.start_api("a")
    cluster.start_api("b")
    cluster.wait_api("a")
    cluster.wait_api("b")
    cluster.wait_workers("a", ["w1"])
    logs = [write_strip_log(tmp_path / "logs" / f"r{seed}.bag", seed=seed, laps=laps)
            for seed, laps in ((5, 4.0), (7, 1.3), (13, 1.3), (17, 1.3))]  # fmt: skip
    first = cluster.upload("a", logs[0], preset="irat")["job"]  # a long job, running through the restarts
    second = cluster.upload("b", logs[1], preset="irat")["job"]
    again = cluster.upload("b", logs[0], preset="irat")  # the same upload at the other replica: the same job
    assert (again["job"], again["duplicate"]) == (first, True)

    cluster.signal("a", signal.SIGKILL)  # replica a dies; b goes on; then a comes back
    third = cluster.upload("b", logs[2], preset="irat")["job"]
    cluster.start_api("a")
    cluster.wait_api("a")
    cluster.signal("b", signal.SIGTERM)  # a clean stop of b while jobs are queued or running
    fourth = cluster.upload("a", logs[3], preset="irat")["job"]

    jobs = [first, second, third, fourth]
    states = cluster.wait_jobs("a", jobs)
    assert [s["status"] for s in states] == ["done"] * 4, states
    rows = _rows(cluster.db_url, Job.id, Job.options)
    assert [r.id for r in rows] == jobs  # no job lost, none queued twice
    assert [r.options["attempts"] for r in rows] == [0] * 4  # no API start reran a job
    assert sorted(s.name for s in _session_names(cluster.db_url)) == ["r13", "r17", "r5", "r7"]


def _session_names(db_url: str) -> list[Any]:
    return _rows(db_url, Session.name)


def test_rabbitmq_works_the_same_way(tmp_path: Path) -> None:
    with local_cluster(tmp_path, RABBITMQ) as rabbit:
        rabbit.start_worker("w1")
        rabbit.start_api("api")
        rabbit.wait_api("api")
        health = rabbit.wait_workers("api", ["w1"])
        assert (health["broker"], health["queue"]) == ("ok", rabbit.queue)
        logs = [write_strip_log(tmp_path / "logs" / f"m{k}" / "twice.bag", laps=laps, t0_ns=t0)
                for k, (laps, t0) in enumerate(((1.3, 1_700_000_000_000_000_000), (1.5, LATER_NS)))]  # fmt: skip
        jobs = [rabbit.upload("api", log, preset="irat")["job"] for log in logs]
        states = rabbit.wait_jobs("api", jobs)
        assert [s["status"] for s in states] == ["done", "done"], states
        # one map key ("twice"): the second ran after the first and merged into its map
        assert [(m["name"], m["sessions"]) for m in rabbit.get("api", "/v1/maps")["maps"]] == [("twice", 2)]

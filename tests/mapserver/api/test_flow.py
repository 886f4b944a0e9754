"""Upload → job done → map listed → experiences → path → export, through HTTP (TestClient)."""

from __future__ import annotations

import heapq
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapserver.params import resolve_params
from mapserver.processing import pipeline
from mapserver.store.health import map_health
from tests.mapserver.api.conftest import Api
from tests.mapserver.api.logs import write_strip_log


def _dijkstra(n: int, links: list[dict[str, Any]], source: int, target: int, key: str) -> float:
    """Independent shortest-path cost (heapq Dijkstra over undirected links, min of parallel links)."""
    adjacency: list[list[tuple[int, float]]] = [[] for _ in range(n)]
    for link in links:
        w = max(float(link[key]), 1e-9)
        adjacency[link["from"]].append((link["to"], w))
        adjacency[link["to"]].append((link["from"], w))
    dist = [float("inf")] * n
    dist[source] = 0.0
    heap = [(0.0, source)]
    while heap:
        d, u = heapq.heappop(heap)
        if d > dist[u]:
            continue
        for v, w in adjacency[u]:
            if d + w < dist[v]:
                dist[v] = d + w
                heapq.heappush(heap, (d + w, v))
    return dist[target]


def test_upload_job_map_path_export(api: Api, strip_log: Path, tmp_path: Path) -> None:
    response = api.upload(strip_log, preset="irat", map="lab")
    assert response.status_code == 202, response.text
    accepted = response.json()
    assert accepted["duplicate"] is False
    assert accepted["session"] is None
    assert accepted["map"] == "lab"
    assert accepted["frames"] == 62

    job = api.wait(accepted["job"])
    assert job["status"] == "done", job
    assert job["progress"] == 1.0
    assert job["session"] == "strip"
    assert job["map"] == "lab"
    assert job["error"] is None

    # the API stored exactly what `process --db` stores for the same log and preset
    expected = pipeline.process_log(strip_log, resolve_params("irat"))
    maps = api.client.get("/v1/maps", headers=api.read).json()["maps"]
    health = maps[0].pop("health")
    assert maps == [{"name": "lab", "sessions": 1, "templates": expected.templates,
                     "experiences": expected.experiences, "links": expected.links,
                     "merges": {"applied": 0, "undone": 0, "rejected": 0, "unverified": 0}}]  # fmt: skip
    # the health figure of the map as stored (core.robust.health over the engine's own snapshot)
    own = map_health(resolve_params("irat"), expected.engine.snapshot())
    assert health == {"switched_off": 0, "links": expected.links, "residual": pytest.approx(own["residual"]),
                      "worst": pytest.approx(own["worst"]), "unmeasured": 0}  # fmt: skip

    detail = api.client.get("/v1/maps/lab", headers=api.read).json()
    assert detail["health"] == {**health, "residual": pytest.approx(health["residual"]),
                                "worst": pytest.approx(health["worst"])}  # fmt: skip
    assert [s["name"] for s in detail["sessions"]] == ["strip"]
    assert detail["sessions"][0]["frames"] == 62
    assert detail["sessions"][0]["status"] == "complete"
    assert detail["merge_events"] == []
    assert detail["experiences"] == expected.experiences

    page = api.client.get("/v1/maps/lab/experiences?offset=2&limit=5", headers=api.read).json()
    assert page["total"] == expected.experiences
    assert [e["id"] for e in page["experiences"]] == [2, 3, 4, 5, 6]
    pose = expected.engine.snapshot()["em_pose"]
    first = page["experiences"][0]
    assert (first["x"], first["y"], first["z"], first["yaw"]) == tuple(pose[2])
    assert first["session"] == "strip"

    document = api.client.get("/v1/maps/lab/export?format=json", headers=api.read)
    assert document.headers["content-type"].startswith("application/json")
    doc = document.json()
    assert doc["format"] == "mapserver-map/1"
    n = len(doc["experiences"])
    last = n - 1
    for weight, key in (("time", "dt"), ("distance", "distance")):
        path = api.client.get(f"/v1/maps/lab/path?from=0&to={last}&weight={weight}", headers=api.read)
        assert path.status_code == 200, path.text
        body = path.json()
        assert body["weight"] == weight
        assert body["nodes"][0] == 0 and body["nodes"][-1] == last
        assert np.isclose(body["cost"], _dijkstra(n, doc["links"], 0, last, key), rtol=1e-12)
        linked = {(link["from"], link["to"]) for link in doc["links"]}
        assert all((a, b) in linked or (b, a) in linked for a, b in zip(body["nodes"], body["nodes"][1:], strict=False))
        assert [[p["x"], p["y"], p["z"], p["yaw"]] for p in body["poses"]] == pose[body["nodes"]].tolist()

    tum = api.client.get("/v1/maps/lab/export?format=tum", headers=api.read)
    assert tum.headers["content-type"].startswith("text/plain")
    rows = [line for line in tum.text.splitlines() if line and not line.startswith("#")]
    assert len(rows) == expected.experiences
    png = api.client.get("/v1/maps/lab/export?format=png", headers=api.read)
    assert png.headers["content-type"] == "image/png"
    assert png.content[:8] == b"\x89PNG\r\n\x1a\n"


def test_reupload_answers_with_the_same_job_and_session(api: Api, strip_log: Path) -> None:
    first = api.upload(strip_log, preset="irat").json()
    done = api.wait(first["job"])
    assert done["status"] == "done"
    again = api.upload(strip_log, preset="irat", headers=api.write)
    assert again.status_code == 202
    body = again.json()
    assert body["job"] == first["job"]
    assert body["duplicate"] is True
    assert body["session"] == done["session"] == "strip"
    assert body["sha256"] == first["sha256"]
    maps = api.client.get("/v1/maps", headers=api.read).json()["maps"]
    assert [(m["name"], m["sessions"]) for m in maps] == [("strip", 1)]
    assert len(list(api.settings.uploads.glob("*/strip.bag"))) == 1
    assert not any((api.settings.uploads / ".incoming").iterdir())


def test_same_file_name_of_another_log_gets_its_own_map(api: Api, tmp_path: Path) -> None:
    a = write_strip_log(tmp_path / "a" / "mission.bag", seed=3)
    b = write_strip_log(tmp_path / "b" / "mission.bag", seed=4)
    jobs = [api.upload(p, preset="irat", merge="false").json()["job"] for p in (a, b)]
    results = [api.wait(j) for j in jobs]
    assert [r["status"] for r in results] == ["done", "done"]
    assert sorted(r["map"] for r in results) == ["mission", "mission-2"]
    assert len({r["session"] for r in results}) == 2


def test_progress_is_the_fraction_of_frames(tmp_path: Path) -> None:
    from mapserver.api.worker import ProgressReporter
    from mapserver.store import open_database
    from mapserver.store.jobs import claim_next_job, create_job, get_job

    with open_database(f"sqlite:///{tmp_path / 'progress.db'}") as db:
        with db.write() as conn:
            create_job(conn=conn, upload_path=str(tmp_path / "x.bag"))
            job = claim_next_job(conn=conn)
        assert job is not None
        reporter = ProgressReporter(db, job.id, interval_s=3600.0, lease_token=job.lease_token)
        reporter(1, 4)  # first call within the interval: not written
        with db.read() as conn:
            assert get_job(conn=conn, job_id=job.id).progress == 0.0
        reporter.interval_s = 0.0
        reporter(3, 4)
        with db.read() as conn:
            assert get_job(conn=conn, job_id=job.id).progress == 0.75
        reporter(4, 4)  # all frames: 0.999 until the result is stored ("done" sets 1.0)
        with db.read() as conn:
            assert get_job(conn=conn, job_id=job.id).progress == 0.999
        assert reporter.writes == 2


def test_job_of_unknown_id_is_404(api: Api) -> None:
    response = api.client.get("/v1/jobs/999", headers=api.read)
    assert response.status_code == 404
    assert response.json() == {"detail": "no job with id 999"}


def test_openapi_and_docs(api: Api) -> None:
    schema = api.client.get("/openapi.json").json()
    ops = {op["operationId"] for path in schema["paths"].values() for op in path.values()}
    assert ops == {"get_health", "upload_session", "get_job", "list_jobs", "list_maps", "get_map", "list_experiences",
                   "find_path", "export_map", "get_metrics", "get_graph_view", "get_nearest_experience",
                   "get_experience", "get_experience_evidence", "list_merges", "get_merge", "undo_merge",
                   "redo_merge", "get_limits", "add_link", "list_links", "move_session",
                   "get_ground_truth_overlay", "delete_map", "restore_map", "rename_map", "read_token"}  # fmt: skip
    assert "multipart/form-data" in schema["paths"]["/v1/sessions"]["post"]["requestBody"]["content"]
    assert api.client.get("/docs").status_code == 200
    assert api.client.get("/healthz").json() == {"status": "ok"}
    assert json.loads(api.client.get("/openapi.json").text)["info"]["title"] == "mapserver"

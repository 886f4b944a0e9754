"""``/metrics`` (Prometheus text) and ``/healthz`` of both engines (issue 15)."""

from __future__ import annotations

import re
import time
from pathlib import Path

from prometheus_client.parser import text_string_to_metric_families

from mapserver.api.cluster import CeleryJobEngine
from mapserver.store import open_database
from tests.mapserver.api.conftest import Api


def _samples(text: str) -> dict[str, float]:
    """Return ``name{labels}`` → value of every sample (parsed by prometheus_client's own parser)."""
    out = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            labels = ",".join(f'{k}="{v}"' for k, v in sorted(sample.labels.items()))
            out[f"{sample.name}{{{labels}}}" if labels else sample.name] = sample.value
    return out


def test_metrics_count_jobs_frames_merges_and_path_queries(api: Api, strip_log: Path) -> None:
    before = _samples(api.client.get("/metrics").text)
    assert before['mapserver_jobs{status="done"}'] == 0
    assert before["mapserver_job_duration_seconds_count"] == 0
    job = api.upload(strip_log, preset="irat", map="lab").json()
    state = api.wait(job["job"])
    assert state["status"] == "done"
    paths_before = before["mapserver_path_query_seconds_count"]
    assert api.client.get("/v1/maps/lab/path?from=0&to=3", headers=api.read).status_code == 200
    assert api.client.get("/v1/maps/lab/path?from=0&to=99999", headers=api.read).status_code == 404

    response = api.client.get("/metrics")
    assert response.headers["content-type"].startswith("text/plain")
    after = _samples(response.text)
    assert after['mapserver_jobs{status="done"}'] == 1
    assert after['mapserver_jobs{status="queued"}'] == 0
    assert after["mapserver_job_frames_total"] == job["frames"] == 62
    assert after["mapserver_job_duration_seconds_count"] == 1
    # the histogram's sum is the job's run time as stored; its rate is frames / that time
    from datetime import datetime

    run_s = (datetime.fromisoformat(state["finished_at"]) - datetime.fromisoformat(state["started_at"])).total_seconds()
    assert abs(after["mapserver_job_duration_seconds_sum"] - run_s) < 1e-3
    assert abs(after["mapserver_job_frames_per_second"] - 62 / run_s) < 1e-3 * 62 / run_s
    assert after['mapserver_merge_events{status="applied"}'] == 0
    assert after["mapserver_path_query_seconds_count"] == paths_before + 2  # answered and refused both timed
    buckets = [v for k, v in after.items() if k.startswith("mapserver_job_duration_seconds_bucket")]
    assert buckets == sorted(buckets) and buckets[-1] == 1  # cumulative


def test_healthz_embedded_is_plain_and_celery_reports_an_unreachable_broker(api: Api, tmp_path: Path) -> None:
    assert api.client.get("/healthz").json() == {"status": "ok"}
    with open_database(f"sqlite:///{tmp_path / 'h.db'}") as db:
        engine = CeleryJobEngine(db, broker_url="redis://127.0.0.1:9/0", queue="nobody")
        started = time.monotonic()
        report = engine.health()
        assert time.monotonic() - started < 15
        assert report["engine"] == "celery" and report["workers"] == []
        assert re.match(r"unreachable: .+", report["broker"]), report
        assert engine.health() is report  # cached for a few seconds
        engine.app.close()

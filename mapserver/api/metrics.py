"""Prometheus metrics (``GET /metrics``): the cluster's jobs and merges from the database, path latency here.

Job and merge figures are read from the database at each scrape, so every API replica reports the
whole cluster (jobs run on other processes); the path-query latency is this process's own.

* ``mapserver_jobs{status}``: jobs by status (gauge).
* ``mapserver_job_duration_seconds``: histogram of done jobs' run time (``finished_at - started_at``).
* ``mapserver_job_frames_total``: frames of done jobs (``rate()`` of it is the cluster's frames/s).
* ``mapserver_job_frames_per_second``: mean frames/s of the last 50 done jobs (per job, on its worker).
* ``mapserver_merge_events{status}``: merge events, applied and undone.
* ``mapserver_path_query_seconds``: latency histogram of ``/v1/maps/{name}/path`` answered here.
"""

from __future__ import annotations

from collections.abc import Iterator

from prometheus_client import CollectorRegistry, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector

from mapserver.store import MERGE_STATUSES, Database
from mapserver.store.jobs import count_jobs, done_job_runs
from mapserver.store.merge_events import count_merge_events

DURATION_BUCKETS = (0.5, 1, 2, 5, 10, 30, 60, 120, 300, 600, 1800, 3600)
RECENT_JOBS = 50

PATH_SECONDS = Histogram(
    "mapserver_path_query_seconds", "latency of shortest-path queries answered by this process",
    buckets=(0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5), registry=None,
)  # fmt: skip


class StoreCollector(Collector):
    """Collects the job and merge metrics from the database at each scrape."""

    def __init__(self, db: Database) -> None:
        self.db = db

    def collect(self) -> Iterator[Metric]:
        """Yield the metric families (one read transaction)."""
        with self.db.read() as conn:
            counts = count_jobs(conn=conn)
            done = done_job_runs(conn=conn)
            merges = count_merge_events(conn=conn)
        jobs = GaugeMetricFamily("mapserver_jobs", "jobs by status", labels=["status"])
        for status, n in counts.items():
            jobs.add_metric([status], n)
        yield jobs
        durations = [max((f - s).total_seconds(), 0.0) for s, f, _o in done]
        frames = [int((o or {}).get("frames") or 0) for _s, _f, o in done]
        yield _histogram("mapserver_job_duration_seconds", "run time of done jobs", durations)
        yield CounterMetricFamily("mapserver_job_frames", "frames of done jobs", value=sum(frames))
        recent = [(n, d) for n, d in zip(frames[-RECENT_JOBS:], durations[-RECENT_JOBS:], strict=True) if d > 0]
        rate = sum(n / d for n, d in recent) / len(recent) if recent else 0.0
        yield GaugeMetricFamily("mapserver_job_frames_per_second",
                                f"mean frames/s of the last {RECENT_JOBS} done jobs", value=rate)  # fmt: skip
        events = GaugeMetricFamily("mapserver_merge_events", "merge events by status", labels=["status"])
        for status in MERGE_STATUSES:
            events.add_metric([status], int(merges.get(status, 0)))
        yield events


def _histogram(name: str, documentation: str, values: list[float]) -> HistogramMetricFamily:
    """Return a histogram family of ``values`` over :data:`DURATION_BUCKETS` (cumulative counts)."""
    buckets = [(str(float(b)), sum(1 for v in values if v <= b)) for b in DURATION_BUCKETS]
    buckets.append(("+Inf", len(values)))
    return HistogramMetricFamily(name, documentation, buckets=buckets, sum_value=sum(values))


def render(db: Database) -> bytes:
    """Return the metrics in Prometheus text format."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(StoreCollector(db))
    registry.register(PATH_SECONDS)
    return generate_latest(registry)

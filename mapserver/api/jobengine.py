"""Job engines: who runs the queued jobs. The embedded default is a thread pool inside the server.

The interface is deliberately narrow (:class:`JobEngine`): the API only *queues* jobs in the database
(``store.jobs.create_job``) and calls :meth:`JobEngine.notify`; everything else — claiming, running,
progress, outcome — goes through the ``jobs`` table, so a distributed engine (workers in other
processes or machines claiming from the same table) can replace :class:`EmbeddedJobEngine` without
touching the routes.

Rules of :class:`EmbeddedJobEngine`:

* ``workers`` threads; each claims the oldest queued job whose map (``jobs.map_name``: the requested
  map, or the log's name) no other thread is running, so jobs that touch the same map run one after
  another and different maps run in parallel. (A session that merges into *another* stored map is
  protected by the store's optimistic map versions, and two sessions processed in parallel still merge
  with each other: the one that writes second sees that the maps it may merge into changed and is
  processed again against them — ``atlas.ensure_candidates_unchanged``.)
* Start (:meth:`start`): jobs left ``running`` by a previous server process — killed, crashed, or
  stopped mid-job — are queued again and rerun from the start (the pipeline stores nothing until its
  single final transaction, so there is nothing half-written to undo), or failed with the reason once
  they have been interrupted ``max_attempts`` times. Then every queued job runs.
* Stop (:meth:`stop`): running jobs are interrupted at their next frame and queued again (nothing of
  theirs was stored), so the next start reruns them. One server process per database: two embedded
  engines on one database would rerun each other's running jobs at start.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Protocol

from sqlalchemy import Connection

from mapserver.api.worker import JobInterrupted, execute_job
from mapserver.errors import MapServerError
from mapserver.store import Database
from mapserver.store.jobs import (
    JobRecord,
    claim_next_job_excluding,
    fail_job,
    finish_job,
    recover_interrupted_jobs,
    requeue_job,
    set_job_dropped,
)

logger = logging.getLogger(__name__)

POLL_S = 2.0
"""A worker also looks for queued jobs this often without being notified (jobs queued by other means)."""


class JobEngine(Protocol):
    """What the API needs from a job engine."""

    def start(self) -> None:
        """Recover interrupted jobs and begin running queued ones."""

    def notify(self) -> None:
        """Tell the engine that a job was queued."""

    def stop(self, timeout: float | None = None) -> None:
        """Stop running jobs (interrupted ones are queued again) and wait up to ``timeout`` seconds."""


class EmbeddedJobEngine:
    """The default engine: a pool of threads in the server process (see the module docstring).

    Args:
        db: the map store (jobs are claimed and updated through it).
        db_url: its URL (the pipeline opens its own connection pool).
        workers: number of threads.
        progress_interval_s: progress is written at most this often per job.
        max_attempts: interruptions after which a job is failed instead of rerun.
    """

    def __init__(
        self, db: Database, *, db_url: str, workers: int, progress_interval_s: float = 0.5, max_attempts: int = 3
    ) -> None:
        self.db = db
        self.db_url = db_url
        self.workers = workers
        self.progress_interval_s = progress_interval_s
        self.max_attempts = max_attempts
        self._cond = threading.Condition()
        self._busy: set[str] = set()
        self._stopping = threading.Event()
        self._threads: list[threading.Thread] = []
        self.recovered: tuple[list[int], list[int]] = ([], [])

    def start(self) -> None:
        """Recover jobs a previous process left running, then start the worker threads."""
        with self.db.write() as conn:
            self.recovered = recover_interrupted_jobs(conn=conn, max_attempts=self.max_attempts)
        requeued, failed = self.recovered
        if requeued or failed:
            logger.warning("jobs interrupted by the last stop: rerunning %s, failed %s", requeued, failed)
        for k in range(self.workers):
            thread = threading.Thread(target=self._loop, name=f"mapserver-job-{k}", daemon=True)
            thread.start()
            self._threads.append(thread)

    def notify(self) -> None:
        """Wake the workers: a job was queued."""
        with self._cond:
            self._cond.notify_all()

    def stop(self, timeout: float | None = 30.0) -> None:
        """Interrupt running jobs (they are queued again) and wait for the threads."""
        self._stopping.set()
        self.notify()
        for thread in self._threads:
            thread.join(timeout)
        self._threads.clear()

    @property
    def busy_maps(self) -> frozenset[str]:
        """Return the maps whose jobs are running now."""
        with self._cond:
            return frozenset(self._busy)

    def _claim(self) -> JobRecord | None:
        """Claim the next runnable job (caller holds ``_cond``) and mark its map busy."""
        try:
            with self.db.write() as conn:
                job = claim_next_job_excluding(conn=conn, busy_maps=self._busy)
        except MapServerError as err:
            logger.error("cannot claim a job: %s", err)
            return None
        if job is not None and job.map_name is not None:
            self._busy.add(job.map_name)
        return job

    def _loop(self) -> None:
        while not self._stopping.is_set():
            with self._cond:
                job = self._claim()
                if job is None:
                    self._cond.wait(POLL_S)
                    continue
            try:
                self._run(job)
            finally:
                with self._cond:
                    if job.map_name is not None:
                        self._busy.discard(job.map_name)
                    self._cond.notify_all()

    def _run(self, job: JobRecord) -> None:
        logger.info("job %d: processing %s", job.id, job.upload_name)
        try:
            outcome = execute_job(
                job, db=self.db, db_url=self.db_url, interval_s=self.progress_interval_s,
                should_stop=self._stopping.is_set,
            )  # fmt: skip
        except JobInterrupted:
            logger.warning("job %d interrupted by the server stop; it will rerun from the start", job.id)
            self._record(lambda conn: requeue_job(conn=conn, job_id=job.id))
            return
        if outcome.error is not None:
            logger.warning("job %d failed: %s", job.id, outcome.error)
            self._record(lambda conn: fail_job(conn=conn, job_id=job.id, error=outcome.error or "failed"))
        else:
            logger.info("job %d done: session %s, map %s", job.id, outcome.session_id, outcome.map_id)

            def done(conn: Connection) -> None:
                finish_job(conn=conn, job_id=job.id, session_id=outcome.session_id, map_id=outcome.map_id)
                if outcome.dropped is not None:
                    set_job_dropped(conn=conn, job_id=job.id, dropped=outcome.dropped)

            self._record(done)

    def _record(self, write: Callable[[Connection], None]) -> None:
        try:
            with self.db.write() as conn:
                write(conn)
        except MapServerError as err:  # the job stays "running" and is recovered at the next start
            logger.error("cannot record a job's outcome: %s", err)

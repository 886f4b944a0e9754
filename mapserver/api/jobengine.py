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
* Leases and fencing: a claim leases the job to this engine (``lease_owner``, ``lease_expires_at``) with
  a new fencing token (``jobs.lease_token``). A lease thread renews the leases every ``lease_s / 3``; every
  progress, outcome and give-back write presents the token (:mod:`mapserver.store.jobs`). A refused write
  or renewal means another engine took the job over: this one stops it at its next frame and writes
  nothing more.
* Recovery (:meth:`start`, and every ``lease_s`` unless ``exclusive``): jobs left ``running`` by a holder
  that is gone — a killed, crashed or stopped server — are queued again and rerun from the start (the
  pipeline stores nothing until its single final transaction, so there is nothing half-written to undo),
  or failed with the reason once they have been interrupted ``max_attempts`` times. ``exclusive`` (the
  server holds the database's server lock, :mod:`mapserver.api.lifecycle`: no other engine can run)
  recovers every running job at start; otherwise (several servers on one PostgreSQL database) only jobs
  whose lease expired are taken over, at start and then periodically. ``mapserver serve`` starts the
  engine only after it has bound its port.
* Stop (:meth:`stop`): running jobs are interrupted at their next frame and queued again (nothing of
  theirs was stored), so the next start reruns them.
"""

from __future__ import annotations

import logging
import os
import secrets
import socket
import threading
import time
from collections.abc import Callable
from typing import Protocol

from mapserver.api.worker import JobInterrupted, LeaseLost, execute_job
from mapserver.errors import MapServerError
from mapserver.store import Connection, Database
from mapserver.store.jobs import (
    JobRecord,
    claim_next_job_excluding,
    fail_job,
    finish_job,
    recover_interrupted_jobs,
    renew_job_leases,
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


def engine_owner() -> str:
    """Return a lease owner name unique to this engine: ``host:pid:random``."""
    return f"{socket.gethostname()}:{os.getpid()}:{secrets.token_hex(3)}"


class EmbeddedJobEngine:
    """The default engine: a pool of threads in the server process (see the module docstring).

    Args:
        db: the map store (jobs are claimed and updated through it; the pipeline writes the sessions through it).
        workers: number of threads.
        progress_interval_s: progress is written at most this often per job.
        max_attempts: interruptions after which a job is failed instead of rerun.
        lease_s: a claimed job's lease; renewed every third of it, taken over by others once expired.
        exclusive: no other job engine runs on this database (the caller holds its server lock): start
            recovers every running job and no periodic recovery runs.
    """

    def __init__(
        self, db: Database, *, workers: int, progress_interval_s: float = 0.5, max_attempts: int = 3,
        lease_s: float = 30.0, exclusive: bool = False,
    ) -> None:  # fmt: skip
        self.db = db
        self.workers = workers
        self.progress_interval_s = progress_interval_s
        self.max_attempts = max_attempts
        self.lease_s = lease_s
        self.exclusive = exclusive
        self.owner = engine_owner()
        self._cond = threading.Condition()
        self._busy: set[str] = set()
        self._leases: dict[int, tuple[int, threading.Event]] = {}
        self._stopping = threading.Event()
        self._threads: list[threading.Thread] = []
        self.recovered: tuple[list[int], list[int]] = ([], [])

    def start(self) -> None:
        """Recover jobs whose holder is gone (see the module docstring), then start the threads."""
        self.recovered = self._recover(expired_only=not self.exclusive)
        requeued, failed = self.recovered
        if requeued or failed:
            logger.warning("jobs interrupted by the last stop: rerunning %s, failed %s", requeued, failed)
        for k in range(self.workers):
            thread = threading.Thread(target=self._loop, name=f"mapserver-job-{k}", daemon=True)
            thread.start()
            self._threads.append(thread)
        thread = threading.Thread(target=self._lease_loop, name="mapserver-job-leases", daemon=True)
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

    def _recover(self, *, expired_only: bool) -> tuple[list[int], list[int]]:
        """Queue again (or fail) running jobs whose holder is gone; return (requeued, failed) ids."""
        try:
            with self.db.write() as conn:
                return recover_interrupted_jobs(conn=conn, max_attempts=self.max_attempts, expired_only=expired_only)
        except MapServerError as err:
            logger.error("cannot recover interrupted jobs: %s", err)
            return [], []

    def _lease_loop(self) -> None:
        """Renew this engine's leases every ``lease_s / 3``; without ``exclusive``, take over expired ones."""
        last_recovery = time.monotonic()
        while not self._stopping.wait(self.lease_s / 3):
            with self._cond:
                leases = dict(self._leases)
            if leases:
                try:
                    with self.db.write() as conn:
                        lost = renew_job_leases(conn=conn, leases={i: t for i, (t, _e) in leases.items()},
                                                lease_s=self.lease_s)  # fmt: skip
                except MapServerError as err:  # retried at the next beat; the lease may lapse meanwhile
                    logger.warning("cannot renew job leases: %s", err)
                    lost = []
                with self._cond:  # a job that ended meanwhile (its lease given up) was not lost
                    lost = [i for i in lost if self._leases.get(i) == leases[i]]
                for job_id in lost:
                    logger.error("job %d: its lease was taken over by another server; stopping it here", job_id)
                    leases[job_id][1].set()
            if not self.exclusive and time.monotonic() - last_recovery >= self.lease_s:
                last_recovery = time.monotonic()
                requeued, failed = self._recover(expired_only=True)
                if requeued or failed:
                    logger.warning("jobs whose server was lost: rerunning %s, failed %s", requeued, failed)
                    self.notify()

    def _claim(self) -> JobRecord | None:
        """Claim the next runnable job (caller holds ``_cond``) and mark its map busy."""
        try:
            with self.db.write() as conn:
                job = claim_next_job_excluding(conn=conn, busy_maps=self._busy, owner=self.owner,
                                               lease_s=self.lease_s)  # fmt: skip
        except MapServerError as err:
            logger.error("cannot claim a job: %s", err)
            return None
        if job is not None:
            if job.map_name is not None:
                self._busy.add(job.map_name)
            self._leases[job.id] = (job.lease_token, threading.Event())
        return job

    def _loop(self) -> None:
        while not self._stopping.is_set():
            with self._cond:
                job = self._claim()
                if job is None:
                    self._cond.wait(POLL_S)
                    continue
                lost = self._leases[job.id][1]
            try:
                self._run(job, lost)
            finally:
                with self._cond:
                    if job.map_name is not None:
                        self._busy.discard(job.map_name)
                    self._leases.pop(job.id, None)
                    self._cond.notify_all()

    def _run(self, job: JobRecord, lost: threading.Event) -> None:
        logger.info("job %d: processing %s", job.id, job.upload_name)
        token = job.lease_token
        try:
            outcome = execute_job(
                job, db=self.db, interval_s=self.progress_interval_s,
                should_stop=lambda: self._stopping.is_set() or lost.is_set(),
            )  # fmt: skip
        except JobInterrupted as stop:
            self._end_lease(job.id)
            if isinstance(stop, LeaseLost) or lost.is_set():
                logger.warning("job %d stopped: another server holds it now (fencing token %d is stale)", job.id, token)
                return
            logger.warning("job %d interrupted by the server stop; it will rerun from the start", job.id)
            self._record(job, lambda conn: requeue_job(conn=conn, job_id=job.id, lease_token=token))
            return
        self._end_lease(job.id)
        if outcome.error is not None:
            logger.warning("job %d failed: %s", job.id, outcome.error)
            self._record(job, lambda conn: fail_job(conn=conn, job_id=job.id, error=outcome.error or "failed",
                                                    lease_token=token))  # fmt: skip
        else:
            logger.info("job %d done: session %s, map %s", job.id, outcome.session_id, outcome.map_id)

            def done(conn: Connection) -> bool:
                held = finish_job(conn=conn, job_id=job.id, session_id=outcome.session_id, map_id=outcome.map_id,
                                  lease_token=token)  # fmt: skip
                if held and outcome.dropped is not None:
                    set_job_dropped(conn=conn, job_id=job.id, dropped=outcome.dropped)
                return held

            self._record(job, done)

    def _end_lease(self, job_id: int) -> None:
        """Stop renewing a job's lease: its run ended, only its (fenced) outcome write is left."""
        with self._cond:
            self._leases.pop(job_id, None)

    def _record(self, job: JobRecord, write: Callable[[Connection], bool]) -> None:
        """Run a fenced write of ``job``'s outcome; log when the token no longer holds the job."""
        try:
            with self.db.write() as conn:
                held = write(conn)
        except MapServerError as err:  # the job stays "running" and is recovered later
            logger.error("cannot record a job's outcome: %s", err)
            return
        if not held:
            logger.warning("job %d: another server took it over; this server's outcome was not recorded", job.id)

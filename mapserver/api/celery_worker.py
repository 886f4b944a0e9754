"""The worker side of the Celery engine: ``drain_map(key)`` runs one map's jobs under its lock.

:func:`drain` takes the map's advisory lock (:class:`mapserver.store.leases.MapLock`) without
waiting — a worker already running that map will run the new job too — and claims the map's
unfinished jobs oldest first. Each job runs with a heartbeat thread that renews its lease and checks
that the lock's connection is alive; if either fails the job is interrupted at its next frame and
nothing of it is stored (the worker that then holds the lock takes it over). After releasing the
lock it looks again for unfinished jobs of the map, so a job queued while the lock was being
released is never left waiting for the next dispatch.
"""

from __future__ import annotations

import logging
import os
import socket
import sys
import threading
from dataclasses import dataclass

from mapserver.api.worker import JobInterrupted, execute_job
from mapserver.store import Database, open_database
from mapserver.store.jobs import JobRecord, set_job_dropped
from mapserver.store.leases import MapLock, claim_map_job, complete_job, has_unfinished, renew_lease

logger = logging.getLogger(__name__)

STALE_RERUNS = 5
"""A job whose pipeline gave up because the maps it may merge into kept changing runs again this often."""


@dataclass(frozen=True, slots=True)
class WorkerConfig:
    """What a worker process needs to run jobs (set by ``mapserver worker`` before the pool starts).

    Attributes:
        db_url: the map store (PostgreSQL).
        name: the worker's name (lease owners are ``name:pid``).
        lease_s: a job's lease; the heartbeat renews it every third of this.
        max_attempts: a job whose worker was lost this many times is failed.
        progress_interval_s: progress is written at most this often per job.
    """

    db_url: str
    name: str = socket.gethostname()
    lease_s: float = 30.0
    max_attempts: int = 3
    progress_interval_s: float = 0.5


_config: WorkerConfig | None = None
_database: tuple[int, Database] | None = None


def configure(config: WorkerConfig) -> None:
    """Set this process's worker configuration (inherited by forked pool processes)."""
    global _config
    _config = config


def _db() -> tuple[WorkerConfig, Database]:
    """Return the configuration and this process's database (opened once per process, after a fork)."""
    global _database
    if _config is None:
        msg = "this process is not a configured mapserver worker (run `mapserver worker`)"
        raise RuntimeError(msg)
    if _database is None or _database[0] != os.getpid():
        _database = (os.getpid(), open_database(_config.db_url))
    return _config, _database[1]


def drain(key: str) -> int:
    """Run the unfinished jobs of map ``key`` while holding its lock; return how many ran here."""
    config, db = _db()
    owner = f"{config.name}:{os.getpid()}"
    ran = 0
    while True:
        lock = MapLock(db, key)
        if not lock.try_acquire():
            return ran  # another worker runs this map and will run its new jobs too
        try:
            ran += _run_claimed(db, lock, key, owner, config)
        finally:
            lock.release()
        with db.read() as conn:
            if not has_unfinished(conn=conn, key=key):
                return ran


def _run_claimed(db: Database, lock: MapLock, key: str, owner: str, config: WorkerConfig) -> int:
    """Claim and run the map's jobs one after another (the caller holds the map's lock)."""
    ran = 0
    while True:
        with db.write() as conn:
            claim = claim_map_job(conn=conn, key=key, owner=owner, lease_s=config.lease_s,
                                  max_attempts=config.max_attempts)  # fmt: skip
        for job_id in claim.failed:
            logger.warning("job %d failed: its worker was lost %d times", job_id, config.max_attempts)
        if claim.job is None:
            return ran
        if claim.taken_over:
            logger.warning("job %d: its worker was lost; rerunning it here", claim.job.id)
        _run_one(db, lock, claim.job, owner, config)
        ran += 1


class _Heartbeat(threading.Thread):
    """Renews a job's lease every ``lease_s / 3`` seconds; sets ``lost`` when the lease or the lock is gone."""

    def __init__(self, db: Database, lock: MapLock, job: JobRecord, owner: str, lease_s: float) -> None:
        super().__init__(name=f"lease-{job.id}", daemon=True)
        self.db, self.lock, self.job_id, self.owner, self.lease_s = db, lock, job.id, owner, lease_s
        self.token = job.lease_token
        self.lost = threading.Event()
        self.done = threading.Event()

    def run(self) -> None:
        while not self.done.wait(self.lease_s / 3):
            try:
                with self.db.write() as conn:
                    held = renew_lease(conn=conn, job_id=self.job_id, owner=self.owner, lease_s=self.lease_s,
                                       lease_token=self.token)  # fmt: skip
            except Exception as err:  # the database is unreachable: the lease will lapse
                logger.warning("job %d: cannot renew its lease: %s", self.job_id, err)
                held = True  # retry; the lock check below decides
            if not held or not self.lock.alive():
                logger.error("job %d: lease or map lock lost; stopping it", self.job_id)
                self.lost.set()
                return


def _run_one(db: Database, lock: MapLock, job: JobRecord, owner: str, config: WorkerConfig) -> None:
    """Run one leased job and record its outcome (only while the lease is still ours)."""
    heartbeat = _Heartbeat(db, lock, job, owner, config.lease_s)
    heartbeat.start()
    try:
        for rerun in range(STALE_RERUNS + 1):
            outcome = execute_job(job, db=db, interval_s=config.progress_interval_s,
                                  should_stop=heartbeat.lost.is_set)  # fmt: skip
            if not outcome.stale or rerun == STALE_RERUNS:
                break
            logger.warning("job %d: %s; running it again", job.id, outcome.error)
    except JobInterrupted:  # the heartbeat or a rejected progress write (LeaseLost) found the lease gone
        logger.warning("job %d interrupted (lease lost); another worker reruns it", job.id)
        return
    finally:
        heartbeat.done.set()
        heartbeat.join()
    with db.write() as conn:
        recorded = complete_job(conn=conn, job_id=job.id, owner=owner, lease_token=job.lease_token,
                                session_id=outcome.session_id, map_id=outcome.map_id, error=outcome.error)  # fmt: skip
        if recorded and outcome.error is None and outcome.dropped is not None:
            set_job_dropped(conn=conn, job_id=job.id, dropped=outcome.dropped)
    if not recorded:
        logger.warning("job %d: its lease was taken over; outcome left to the new owner", job.id)
    elif outcome.error is not None:
        logger.warning("job %d failed: %s", job.id, outcome.error)
    else:
        logger.info("job %d done: session %s, map %s", job.id, outcome.session_id, outcome.map_id)


def one_core_per_job() -> None:
    """Limit this process's numeric libraries (BLAS, OpenMP, OpenCV, torch) to one thread each.

    A worker runs ``--concurrency`` jobs at once, one per core: library thread pools on top of that
    would oversubscribe the cores. The engine's own frame loop already limits BLAS (``mapserver.processing.run``);
    this covers the rest of a job (store, merge, relaxation) and the other libraries. (Measured with
    ``bench/cluster.py``, 2 workers on 2 cores: within the noise on its own; the slowdown of jobs under 2
    workers came mostly from the bench's own polling, docs/scaling.md.)
    """
    import cv2
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)
    cv2.setNumThreads(1)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")  # for torch when a job imports it later


def serve_worker(*, broker_url: str, queue: str, name: str, concurrency: int, pool: str, log_level: str) -> int:
    """Run a Celery worker on ``queue`` until it is stopped (call :func:`configure` first); return 0.

    Besides the pool, the worker's main process runs a :class:`mapserver.api.cluster.Dispatcher`, so
    jobs whose worker was lost are dispatched again even when no API server runs.
    """
    from celery import signals

    from mapserver.api.cluster import Dispatcher, make_celery

    if _config is None:
        msg = "call configure() before serve_worker()"
        raise RuntimeError(msg)
    config = _config  # the pool processes open their own databases after the fork (see _db)
    app = make_celery(broker_url, queue)
    dispatchers: list[Dispatcher] = []

    def start_dispatcher(**_kwargs: object) -> None:
        db = open_database(config.db_url)
        interval = max(0.5, min(config.lease_s / 2, 10.0))
        dispatcher = Dispatcher(db, app, queue=queue, redispatch_s=2 * config.lease_s, interval_s=interval)
        dispatcher.start()
        dispatchers.append(dispatcher)

    def stop_dispatcher(**_kwargs: object) -> None:
        for dispatcher in dispatchers:
            dispatcher.stop()
            dispatcher.db.dispose()

    signals.worker_process_init.connect(lambda **_kwargs: one_core_per_job(), weak=False)  # prefork children
    one_core_per_job()  # solo and threads pools run jobs in this process
    signals.worker_ready.connect(start_dispatcher, weak=False)
    signals.worker_shutdown.connect(stop_dispatcher, weak=False)
    app.worker_main([
        "worker", f"--concurrency={concurrency}", f"--queues={queue}", f"--hostname={name}", f"--pool={pool}",
        f"--loglevel={log_level.upper()}", "--without-gossip", "--without-mingle",
    ])  # fmt: skip
    return 0

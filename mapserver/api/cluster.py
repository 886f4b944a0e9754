"""The Celery job engine (issue 15): jobs run on ``mapserver worker`` processes, over PostgreSQL.

The ``jobs`` table stays the source of truth (status, progress, attempts in ``options.attempts``,
errors, leases); the broker (Redis by default, RabbitMQ the same way) only carries *wake-up calls*:
a message ``drain_map(key)`` says "map ``key`` has work". The worker that takes the map's advisory
lock runs that map's unfinished jobs oldest first (:mod:`mapserver.api.celery_worker`), so jobs of
one map run one after another across all workers and different maps run in parallel.

Delivery is at least once (late acknowledgement, ``reject_on_worker_lost``, the broker's redelivery
of unacknowledged messages, and :class:`Dispatcher`, which re-sends messages for queued jobs not
started within ``redispatch_s`` and for running jobs whose lease expired). Effects are exactly once:
a job is claimed in the database under its map's lock, its outcome is written only by its lease
owner, and the pipeline stores a session in one transaction and answers a re-run of a stored log
with the stored session. A duplicate message finds the lock taken or nothing to claim and returns.

Any number of ``serve`` processes may share one database and broker: none of them reruns or
recovers jobs at start; each runs a :class:`Dispatcher` (duplicate messages are harmless).
"""

from __future__ import annotations

import logging
import re
import threading
import time
from typing import Any

from celery import Celery

from mapserver.errors import MapServerError
from mapserver.store import Database
from mapserver.store.leases import due_job_maps

logger = logging.getLogger(__name__)

DEFAULT_BROKER = "redis://127.0.0.1:6379/0"
DEFAULT_QUEUE = "mapserver"
TASK_NAME = "mapserver.drain_map"
VISIBILITY_TIMEOUT_S = 3600
"""Redis: an unacknowledged message is delivered again after this long (a lost worker's lease expires sooner)."""


def make_celery(broker_url: str, queue: str = DEFAULT_QUEUE) -> Celery:
    """Return the Celery application of mapserver (broker, queue, late acknowledgement, no result backend)."""
    app = Celery("mapserver", broker=broker_url, set_as_current=False)
    app.conf.update(
        task_default_queue=queue,
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        task_acks_on_failure_or_timeout=True,
        task_ignore_result=True,
        task_serializer="json",
        accept_content=["json"],
        worker_prefetch_multiplier=1,
        worker_hijack_root_logger=False,
        broker_connection_retry_on_startup=True,
        broker_connection_timeout=3,
        broker_transport_options={"visibility_timeout": VISIBILITY_TIMEOUT_S},
        task_publish_retry_policy={"max_retries": 3, "interval_start": 0.1, "interval_step": 0.3},
    )

    @app.task(name=TASK_NAME)
    def drain_map(key: str) -> None:
        from mapserver.api.celery_worker import drain  # the worker process's context

        drain(key)

    return app


_URL = re.compile(r"\b[A-Za-z][A-Za-z0-9+.-]*://\S+")


def broker_problem(err: BaseException) -> str:
    """Return the health report's word for an unreachable broker: the transport's reason, any URL in it replaced.

    ``unreachable: <reason>`` on one line, at most 200 characters of reason; a URL the reason quotes (which may
    hold a user name or a host) reads ``<broker>``, the log keeps the whole text.
    """
    reason = _URL.sub("<broker>", " ".join(str(err).split()))
    return f"unreachable: {reason[:200]}"


class Dispatcher:
    """A thread that sends a ``drain_map`` message for every map with due jobs (see :func:`due_job_maps`).

    It runs every ``interval_s`` seconds and at once after :meth:`wake`.
    """

    def __init__(self, db: Database, app: Celery, *, queue: str, redispatch_s: float, interval_s: float) -> None:
        self.db = db
        self.app = app
        self.queue = queue
        self.redispatch_s = redispatch_s
        self.interval_s = interval_s
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.sent = 0

    def start(self) -> None:
        """Start the thread (one dispatch at once)."""
        self._wake.set()
        self._thread = threading.Thread(target=self._loop, name="mapserver-dispatch", daemon=True)
        self._thread.start()

    def wake(self) -> None:
        """Dispatch now (non-blocking: safe on the event loop)."""
        self._wake.set()

    def stop(self, timeout: float | None = 10.0) -> None:
        """Stop the thread."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def dispatch_once(self) -> list[str]:
        """Mark due jobs dispatched and send one message per map; return the map keys sent."""
        with self.db.write() as conn:
            keys = due_job_maps(conn=conn, redispatch_s=self.redispatch_s)
        for key in keys:
            self.app.send_task(TASK_NAME, args=[key], queue=self.queue)
        self.sent += len(keys)
        return keys

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(self.interval_s)
            self._wake.clear()
            if self._stop.is_set():
                return
            try:
                keys = self.dispatch_once()
            except (MapServerError, OSError, Exception) as err:  # the broker or database is down: retry later
                logger.warning("cannot dispatch jobs: %s", err)
                continue
            if keys:
                logger.info("dispatched maps %s", keys)


class CeleryJobEngine:
    """The API side of the Celery engine: dispatches queued jobs and reports the broker and workers.

    Args:
        db: the map store (PostgreSQL).
        broker_url: Celery broker URL (``redis://…`` or ``amqp://…``).
        queue: the queue the workers consume.
        lease_s: the workers' lease; a queued job not started after twice this is dispatched again.
    """

    def __init__(self, db: Database, *, broker_url: str, queue: str = DEFAULT_QUEUE, lease_s: float = 30.0) -> None:
        self.db = db
        self.broker_url = broker_url
        self.queue = queue
        self.app = make_celery(broker_url, queue)
        interval = max(0.5, min(lease_s / 2, 10.0))
        self.dispatcher = Dispatcher(db, self.app, queue=queue, redispatch_s=2 * lease_s, interval_s=interval)
        self._health: tuple[float, dict[str, Any]] | None = None
        self._health_lock = threading.Lock()

    def start(self) -> None:
        """Start dispatching (no recovery: leases make that the workers' business)."""
        self.dispatcher.start()

    def notify(self) -> None:
        """A job was queued: dispatch now."""
        self.dispatcher.wake()

    def stop(self, timeout: float | None = 10.0) -> None:
        """Stop dispatching; running jobs go on on their workers."""
        self.dispatcher.stop(timeout)
        self.app.close()

    def health(self, max_age_s: float = 3.0) -> dict[str, Any]:
        """Return ``{"engine", "broker", "queue", "workers"}``: broker reachability and the workers seen on the queue.

        Workers are those answering a broadcast within 1 s that consume this engine's queue; the answer
        is cached ``max_age_s`` seconds.
        """
        with self._health_lock:
            if self._health is not None and time.monotonic() - self._health[0] < max_age_s:
                return self._health[1]
            report = self._probe()
            self._health = (time.monotonic(), report)
            return report

    def _probe(self) -> dict[str, Any]:
        report: dict[str, Any] = {"engine": "celery", "queue": self.queue, "broker": "ok", "workers": []}
        try:
            with self.app.connection_for_write() as conn:
                conn.ensure_connection(max_retries=1, timeout=2)
            replies = self.app.control.inspect(timeout=1.0).active_queues() or {}
        except Exception as err:  # a broker that cannot be reached, whatever the transport says
            logger.warning("the broker cannot be reached: %s", err)
            report["broker"] = broker_problem(err)
            return report
        report["workers"] = sorted(
            name for name, queues in replies.items() if any(q.get("name") == self.queue for q in queues or [])
        )
        return report

"""Running one job: the uploaded log through :func:`mapserver.processing.pipeline.process_into_store`.

This is the whole unit of work a job engine executes (the embedded thread pool today, a distributed
worker later): given the job's record it resolves the parameters, picks the map name, runs the
pipeline with a throttled progress reporter, and returns the outcome. The pipeline writes the
session, map state and any merge in one transaction, so an interrupted job leaves nothing behind and
can simply be run again from the start.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from core.config import ConfigError
from mapserver.api.requestid import internal_error_detail, new_request_id
from mapserver.errors import MapServerError
from mapserver.ingest import LogIdentity, open_log
from mapserver.names import default_map_name, unique_map_name
from mapserver.params import resolve_params
from mapserver.processing import pipeline
from mapserver.store import Database, StaleMapError, find_map, find_session
from mapserver.store.admission import pending_map_creator
from mapserver.store.jobs import JobRecord, set_job_progress

logger = logging.getLogger(__name__)


class JobInterrupted(Exception):  # noqa: N818 - a control-flow signal, not an error
    """Raised inside a running job when the engine stops; the job is queued again."""


class LeaseLost(JobInterrupted):
    """Raised inside a running job whose progress write was refused: another holder has the job now.

    The job is not queued again by this holder (its writes are fenced off); the new holder runs it.
    """


@dataclass(frozen=True, slots=True)
class JobOutcome:
    """What a finished job produced: the session and map ids, or the one-line error.

    ``stale``: the error is the pipeline's last :class:`~mapserver.store.StaleMapError` (maps it may merge
    into kept changing while it ran); running the job again may succeed. ``dropped``: what reading the log
    dropped (``IngestReport.as_dict()``), None when nothing was.
    """

    session_id: int | None = None
    map_id: int | None = None
    error: str | None = None
    stale: bool = False
    dropped: dict[str, Any] | None = None


class ProgressReporter:
    """``progress(done, total)`` for the pipeline: writes the fraction of frames done, throttled.

    A write happens when ``interval_s`` has passed since the last one (and for the last frame), so a
    long log costs a handful of small transactions, not one per frame. ``should_stop()`` is checked on
    every frame; when it returns True the job is interrupted (:class:`JobInterrupted`). Each write presents
    the job's fencing token; a refused write means the job was taken over (:class:`LeaseLost`).
    """

    def __init__(
        self, db: Database, job_id: int, *, interval_s: float, should_stop: Callable[[], bool] | None = None,
        lease_token: int = 0,
    ) -> None:  # fmt: skip
        self.db = db
        self.job_id = job_id
        self.lease_token = lease_token
        self.interval_s = interval_s
        self.should_stop = should_stop
        self._last_write = time.monotonic()
        self.writes = 0

    def __call__(self, done: int, total: int) -> None:
        """Record that ``done`` of ``total`` frames are processed (throttled)."""
        if self.should_stop is not None and self.should_stop():
            raise JobInterrupted
        now = time.monotonic()
        if total <= 0 or (done < total and now - self._last_write < self.interval_s):
            return
        fraction = min(done / total, 1.0)
        if done >= total:
            fraction = min(fraction, 0.999)  # "done" (1.0) is set when the result is stored
        with self.db.write() as conn:
            held = set_job_progress(conn=conn, job_id=self.job_id, progress=fraction, lease_token=self.lease_token)
        if not held:
            raise LeaseLost
        self._last_write = now
        self.writes += 1


def job_identity(job: JobRecord, log_path: Path) -> LogIdentity:
    """Return the log identity the job's upload recorded (``options["log"]``, read when the upload was checked).

    A job queued without one (by an older server) has its log opened and hashed here, once.
    """
    recorded = LogIdentity.from_dict((job.options or {}).get("log"))
    if recorded is not None:
        return recorded
    with open_log(log_path, job.topics) as log:
        return LogIdentity.of(log)


def _map_name(db: Database, job: JobRecord, log_path: Path, identity: LogIdentity) -> str | None:
    """Return the map name to pass to the pipeline.

    An explicit ``map`` is passed as given; a job sent ``into`` a map names none. Without either, the log's
    name is used, made unique (``name-2``, ...) when a map of that name exists (live or archived: an
    archived map keeps its name) or a pending job's request names it — unless this log is stored already
    (then the pipeline continues or answers with its session and needs no name).
    """
    options = job.options or {}
    if options.get("map_given"):
        return job.map_name
    if options.get("into") is not None:  # merged into that map: no new map is named
        return None
    base = job.map_name or default_map_name(log_path)
    with db.read() as conn:
        if find_session(conn=conn, log_sha256=identity.sha256, topics=identity.mapping) is not None:
            return None

        def taken(name: str) -> bool:
            return (
                find_map(conn=conn, name=name, archived=None) is not None
                or pending_map_creator(conn=conn, name=name, except_job=job.id) is not None
            )

        return unique_map_name(base, taken)


def _internal_error(job: JobRecord, err: Exception) -> str:
    """Log a job's internal failure under its upload's request id; return the job's error naming only that id."""
    reference = str((job.options or {}).get("request_id") or new_request_id())
    logger.error("job %d failed (reference %s): %s", job.id, reference, err, exc_info=err)
    return internal_error_detail(reference)


def execute_job(
    job: JobRecord, *, db: Database, interval_s: float, should_stop: Callable[[], bool] | None = None
) -> JobOutcome:
    """Process a job's log into the store; return the outcome (errors become ``JobOutcome.error``).

    ``db`` is the process's database (the server's, or the worker's): the pipeline writes through it too.

    Raises:
        JobInterrupted: ``should_stop`` turned True while the log was being processed (nothing stored).
        LeaseLost: a progress write was refused: the job's fencing token moved on (another holder runs it).
    """
    log_path = Path(job.upload_path)
    reporter = ProgressReporter(db, job.id, interval_s=interval_s, should_stop=should_stop,
                                lease_token=job.lease_token)  # fmt: skip
    try:
        if not log_path.exists():
            msg = f"the uploaded log is gone from the server ({log_path.name!r}); upload it again"
            return JobOutcome(error=msg)
        params = resolve_params(job.preset)
        identity = job_identity(job, log_path)
        result = pipeline.process_into_store(
            log_path,
            params,
            db_url=None,
            db=db,
            identity=identity,
            map_name=_map_name(db, job, log_path, identity),
            topics=job.topics,
            merge=bool((job.options or {}).get("merge", True)),
            progress=reporter,
            into=(job.options or {}).get("into"),
        )
    except JobInterrupted:
        raise
    except (MapServerError, ConfigError) as err:
        if isinstance(err, MapServerError) and err.http_status >= 500:  # the server's own failure: text to the log
            return JobOutcome(error=_internal_error(job, err))
        return JobOutcome(error=str(err).replace(str(log_path.parent) + "/", ""), stale=isinstance(err, StaleMapError))
    except Exception as err:
        return JobOutcome(error=_internal_error(job, err))
    with db.read() as conn:
        record = find_map(conn=conn, name=result.map_name)
    warning = None if result.dropped is None else result.dropped.warning()
    if warning is not None:
        logger.warning("job %d: %s", job.id, warning)
    dropped = None if warning is None or result.dropped is None else result.dropped.as_dict()
    return JobOutcome(session_id=result.session_id, map_id=None if record is None else record.id, dropped=dropped)

"""What the running server holds: settings, the database, the job engine, the graph cache.

Created by the application's lifespan (:func:`mapserver.api.app.create_app`), never at import time.
"""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

from mapserver.api.graphs import GraphCache
from mapserver.api.intake import StoredLog, UploadOptions
from mapserver.api.jobengine import EmbeddedJobEngine, JobEngine
from mapserver.api.settings import Settings
from mapserver.api.uploads import ReceivedUpload
from mapserver.errors import ConflictError, MapServerError
from mapserver.ingest import open_log
from mapserver.store import Database, open_database
from mapserver.store.admission import UploadClaim, admission_conflict, lock_admission
from mapserver.store.jobs import JobRecord, create_job, find_upload_job, lock_upload
from mapserver.store.tokens import LAST_USED_RESOLUTION_S, mark_token_used

logger = logging.getLogger(__name__)


def _job_engine(settings: Settings, db: Database) -> JobEngine:
    """Return the job engine the settings name (``embedded`` threads, or ``celery`` workers)."""
    if settings.jobs == "celery":
        from mapserver.api.cluster import CeleryJobEngine

        return CeleryJobEngine(db, broker_url=settings.broker_url, queue=settings.job_queue, lease_s=settings.lease_s)
    return EmbeddedJobEngine(
        db, db_url=settings.db_url, workers=settings.workers,
        progress_interval_s=settings.progress_interval_s, max_attempts=settings.max_job_attempts,
    )  # fmt: skip


@dataclass
class Services:
    """The server's long-lived objects (one per application)."""

    settings: Settings
    db: Database
    jobs: JobEngine
    graphs: GraphCache
    _touch: ThreadPoolExecutor = field(default_factory=lambda: ThreadPoolExecutor(1, thread_name_prefix="token-touch"))
    _touched: dict[int, float] = field(default_factory=dict)
    _touch_lock: threading.Lock = field(default_factory=threading.Lock)

    @classmethod
    def start(cls, settings: Settings) -> Services:
        """Open the database (an empty one gets the schema), start the job engine, return the services.

        Raises:
            StoreError: the database is unreachable or at another schema revision.
        """
        db = open_database(settings.db_url)
        try:
            settings.uploads.mkdir(parents=True, exist_ok=True)
            engine = _job_engine(settings, db)
            engine.start()
        except BaseException:
            db.dispose()
            raise
        return cls(settings=settings, db=db, jobs=engine, graphs=GraphCache(db, settings.graph_cache_maps))

    def close(self) -> None:
        """Stop the job engine (running jobs are queued again) and close the database."""
        self.jobs.stop()
        self._touch.shutdown(wait=True)
        self.db.dispose()

    # -- uploads ---------------------------------------------------------------------------------------
    @staticmethod
    def job_options(options: UploadOptions) -> dict[str, object]:
        """Return the ``jobs.options`` of an upload (what, besides bytes, topics and preset, makes it distinct)."""
        return {"merge": options.merge, "map_given": options.map_name is not None, "requested_map": options.map_name}

    def find_duplicate(self, upload: ReceivedUpload, options: UploadOptions) -> JobRecord | None:
        """Return the job of an earlier identical upload (same bytes and request), unless it failed."""
        with self.db.read() as conn:
            return find_upload_job(
                conn=conn, upload_sha256=upload.sha256, topics=options.topics, preset=options.preset,
                options=self.job_options(options),
            )  # fmt: skip

    def check_admission(self, upload: ReceivedUpload, options: UploadOptions) -> None:
        """Refuse an upload whose job would fail for a reason known before its log is opened (409).

        Raises:
            ConflictError: another pending job processes the same log, or creates the map asked for.
        """
        claim = UploadClaim(upload.sha256, options.topics, options.map_name)
        with self.db.read() as conn:
            reason = admission_conflict(conn=conn, claim=claim)
        if reason is not None:
            raise ConflictError(reason)

    def queue_job(
        self, upload: ReceivedUpload, log: StoredLog, options: UploadOptions, request_id: str | None = None
    ) -> tuple[JobRecord, bool]:
        """Queue a job for a stored log, or return the job of an identical upload queued meanwhile.

        The duplicate check, the admission check (:func:`mapserver.store.admission.admission_conflict`) and
        the insert are one write transaction under the admission lock, so concurrent uploads are decided
        one after the other. ``request_id`` (the upload's) is kept in ``options``: an internal failure of
        the job names it.

        Returns:
            (the job, True when it is an earlier upload's job).

        Raises:
            ConflictError: the job would fail for a reason known now (the message says which).
        """
        identity = _log_sha256(upload, log, options)
        claim = UploadClaim(upload.sha256, options.topics, options.map_name, identity, log.mapping)
        with self.db.write() as conn:
            lock_admission(conn=conn)
            lock_upload(conn=conn, upload_sha256=upload.sha256)
            existing = find_upload_job(
                conn=conn, upload_sha256=upload.sha256, topics=options.topics, preset=options.preset,
                options=self.job_options(options),
            )  # fmt: skip
            if existing is not None:
                return existing, True
            reason = admission_conflict(conn=conn, claim=claim)
            if reason is not None:
                raise ConflictError(reason)
            job = create_job(
                conn=conn,
                upload_path=str(log.path.resolve()),
                upload_name=upload.filename,
                upload_sha256=upload.sha256,
                map_name=options.map_name or log.name,
                preset=options.preset,
                topics=options.topics,
                options={**self.job_options(options), "frames": log.frames, "attempts": 0, "request_id": request_id},
            )
        return job, False

    # -- tokens ----------------------------------------------------------------------------------------
    def touch_token(self, token_id: int, last_used: float | None) -> None:
        """Record a token's use in the background, at most every few minutes per token."""
        now = time.time()
        with self._touch_lock:
            previous = self._touched.get(token_id, last_used or 0.0)
            if now - previous < LAST_USED_RESOLUTION_S:
                return
            self._touched[token_id] = now
        self._touch.submit(self._mark_used, token_id)

    def _mark_used(self, token_id: int) -> None:
        try:
            with self.db.write() as conn:
                mark_token_used(conn=conn, token_id=token_id)
        except MapServerError as err:  # bookkeeping only: never fail a request for it
            logger.warning("cannot record the use of token %d: %s", token_id, err)


def _log_sha256(upload: ReceivedUpload, log: StoredLog, options: UploadOptions) -> str:
    """Return the log's identity: the upload's SHA-256 for a log uploaded as it is, else the unpacked log's."""
    if log.path == log.folder / upload.filename:
        return upload.sha256
    with open_log(log.path, options.topics) as opened:
        return opened.sha256

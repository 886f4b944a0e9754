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
from mapserver.api.housekeeping import Janitor, describe, remove_leftovers
from mapserver.api.intake import StoredLog, UploadOptions
from mapserver.api.jobengine import EmbeddedJobEngine, JobEngine
from mapserver.api.lifecycle import ServerLock
from mapserver.api.settings import Settings
from mapserver.api.uploads import ReceivedUpload
from mapserver.atlas import merge_target_problem
from mapserver.errors import ConflictError, MapServerError
from mapserver.params import resolve_params
from mapserver.store import Connection, Database, open_database
from mapserver.store.admission import UploadClaim, admission_refusal, lock_admission
from mapserver.store.jobs import JobRecord, create_job, find_upload_job, lock_upload
from mapserver.store.tokens import LAST_USED_RESOLUTION_S, mark_token_used

logger = logging.getLogger(__name__)


def _job_engine(settings: Settings, db: Database, *, exclusive: bool) -> JobEngine:
    """Return the job engine the settings name (``embedded`` threads, or ``celery`` workers).

    ``exclusive``: this server holds the database's server lock (no other embedded engine on it).
    """
    if settings.jobs == "celery":
        from mapserver.api.cluster import CeleryJobEngine

        return CeleryJobEngine(db, broker_url=settings.broker_url, queue=settings.job_queue, lease_s=settings.lease_s)
    return EmbeddedJobEngine(
        db, workers=settings.workers,
        progress_interval_s=settings.progress_interval_s, max_attempts=settings.max_job_attempts,
        lease_s=settings.lease_s, exclusive=exclusive,
    )  # fmt: skip


@dataclass
class Services:
    """The server's long-lived objects (one per application)."""

    settings: Settings
    db: Database
    jobs: JobEngine
    graphs: GraphCache
    janitor: Janitor | None = None
    server_lock: ServerLock | None = None
    _touch: ThreadPoolExecutor = field(default_factory=lambda: ThreadPoolExecutor(1, thread_name_prefix="token-touch"))
    _touched: dict[int, float] = field(default_factory=dict)
    _touch_lock: threading.Lock = field(default_factory=threading.Lock)

    @classmethod
    def start(cls, settings: Settings, server_lock: ServerLock | None = None) -> Services:
        """Open the database, take its server lock, clean the upload directory, start the job engine.

        ``server_lock``: the lock ``mapserver serve`` took already; without it the lock the settings need
        (SQLite with embedded jobs) is taken here. :meth:`close` releases either. Holding it, this server is
        the only one on the database: leftovers of a killed server (staged ``.part`` files, folders no job
        names) are removed before the engine starts and recovers the jobs it left running. The retention
        of processed uploads (:class:`~mapserver.api.housekeeping.Janitor`) starts last.

        Raises:
            StoreError: the database is unreachable or at another schema revision.
            ConflictError: another server holds the database's server lock.
        """
        db = open_database(settings.db_url)
        own = None if server_lock is not None else ServerLock.for_settings(settings)
        try:
            if own is not None:
                own.acquire()
            exclusive = server_lock is not None or own is not None
            settings.uploads.mkdir(parents=True, exist_ok=True)
            if exclusive:
                removed = remove_leftovers(db, settings.uploads, grace_s=0.0)
                if removed:
                    logger.warning("removed uploads left by a stopped server: %s", describe(removed))
            engine = _job_engine(settings, db, exclusive=exclusive)
            engine.start()
            janitor = Janitor(db, settings.uploads, keep_s=settings.keep_uploads_days * 86400.0)
            janitor.start()
        except BaseException:
            if own is not None:
                own.release()
            db.dispose()
            raise
        graphs = GraphCache(db, settings.graph_cache_maps)
        held = server_lock if server_lock is not None else own
        return cls(settings=settings, db=db, jobs=engine, graphs=graphs, janitor=janitor, server_lock=held)

    def close(self) -> None:
        """Stop the job engine (running jobs are queued again) and the housekeeping; close the database.

        The server lock is released last: nothing of this server touches the jobs any more.
        """
        self.jobs.stop()
        if self.janitor is not None:
            self.janitor.stop()
        self._touch.shutdown(wait=True)
        self.db.dispose()
        if self.server_lock is not None:
            self.server_lock.release()

    # -- uploads ---------------------------------------------------------------------------------------
    @staticmethod
    def job_options(options: UploadOptions) -> dict[str, object]:
        """Return the ``jobs.options`` of an upload (what, besides bytes, topics and preset, makes it distinct)."""
        into = {} if options.into is None else {"into": options.into}
        return {"merge": options.merge, "map_given": options.map_name is not None, "requested_map": options.map_name,
                **into}  # fmt: skip

    def find_duplicate(self, upload: ReceivedUpload, options: UploadOptions) -> JobRecord | None:
        """Return the job of an earlier identical upload (same bytes and request), unless it failed."""
        with self.db.read() as conn:
            return find_upload_job(
                conn=conn, upload_sha256=upload.sha256, topics=options.topics, preset=options.preset,
                options=self.job_options(options),
            )  # fmt: skip

    def check_admission(self, upload: ReceivedUpload, options: UploadOptions) -> None:
        """Refuse an upload whose job would fail for a reason known before its log is opened (404, 409).

        Raises:
            ConflictError: another pending job processes the same log, or creates the map asked for; the map
                to merge into is archived, has a partial session or parameters the preset cannot merge with.
            NotFoundError: no map to merge into of that name.
        """
        claim = UploadClaim(upload.sha256, options.topics, options.map_name, into=options.into)
        with self.db.read() as conn:
            refusal = admission_refusal(conn=conn, claim=claim) or _into_params_refusal(conn, options)
        if refusal is not None:
            raise refusal

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
        identity = log.identity
        claim = UploadClaim(upload.sha256, options.topics, options.map_name, identity.sha256, identity.mapping,
                            options.into)  # fmt: skip
        with self.db.write() as conn:
            lock_admission(conn=conn)
            lock_upload(conn=conn, upload_sha256=upload.sha256)
            existing = find_upload_job(
                conn=conn, upload_sha256=upload.sha256, topics=options.topics, preset=options.preset,
                options=self.job_options(options),
            )  # fmt: skip
            if existing is not None:
                return existing, True
            refusal = admission_refusal(conn=conn, claim=claim) or _into_params_refusal(conn, options)
            if refusal is not None:
                raise refusal
            job = create_job(
                conn=conn,
                upload_path=str(log.path.resolve()),
                upload_name=upload.filename,
                upload_sha256=upload.sha256,
                map_name=options.into or options.map_name or log.name,
                preset=options.preset,
                topics=options.topics,
                options={**self.job_options(options), "frames": identity.frames, "attempts": 0,
                         "request_id": request_id, "log": identity.as_dict()},
            )  # fmt: skip
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


def _into_params_refusal(conn: Connection, options: UploadOptions) -> ConflictError | None:
    """Return the 409 when the map to merge into cannot take a session of the upload's preset."""
    if options.into is None:
        return None
    problem = merge_target_problem(conn, name=options.into, params=resolve_params(options.preset))
    return None if problem is None else ConflictError(f"map {options.into!r} cannot take this session: {problem}")

"""Processing jobs of the REST API (issue 6): queued uploads, claimed by a worker, progress, outcome."""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import Connection, func, insert, select, text, update

from mapserver.errors import NotFoundError
from mapserver.store.models import JOB_STATUSES, Job, utcnow


@dataclass(frozen=True, slots=True)
class JobRecord:
    """A stored job (``status``: queued, running, done or failed; ``progress`` in [0, 1])."""

    id: int
    status: str
    progress: float
    error: str | None
    session_id: int | None
    map_id: int | None
    map_name: str | None
    upload_path: str
    upload_name: str | None
    upload_sha256: str | None
    preset: str | None
    topics: dict[str, Any] | None
    options: dict[str, Any] | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


def _record(row: Any) -> JobRecord:
    return JobRecord(
        id=int(row.id),
        status=row.status,
        progress=float(row.progress),
        error=row.error,
        session_id=row.session_id,
        map_id=row.map_id,
        map_name=row.map_name,
        upload_path=row.upload_path,
        upload_name=row.upload_name,
        upload_sha256=row.upload_sha256,
        preset=row.preset,
        topics=row.topics,
        options=row.options,
        created_at=row.created_at,
        started_at=row.started_at,
        finished_at=row.finished_at,
    )


def create_job(
    *,
    conn: Connection,
    upload_path: str,
    upload_name: str | None = None,
    upload_sha256: str | None = None,
    map_name: str | None = None,
    preset: str | None = None,
    topics: Mapping[str, Any] | None = None,
    options: Mapping[str, Any] | None = None,
) -> JobRecord:
    """Queue a job for an uploaded log; return it."""
    now = utcnow()
    job_id = conn.execute(
        insert(Job)
        .values(
            status="queued",
            progress=0.0,
            upload_path=upload_path,
            upload_name=upload_name,
            upload_sha256=upload_sha256,
            map_name=map_name,
            preset=preset,
            topics=None if topics is None else dict(topics),
            options=None if options is None else dict(options),
            created_at=now,
            updated_at=now,
        )
        .returning(Job.id)
    ).scalar_one()
    return get_job(conn=conn, job_id=int(job_id))


def get_job(*, conn: Connection, job_id: int) -> JobRecord:
    """Return a job.

    Raises:
        NotFoundError: no such job.
    """
    row = conn.execute(select(Job.__table__).where(Job.id == job_id)).first()
    if row is None:
        msg = f"no job with id {job_id!r}"
        raise NotFoundError(msg)
    return _record(row)


def claim_next_job(*, conn: Connection) -> JobRecord | None:
    """Mark the oldest queued job ``running`` and return it (None when the queue is empty).

    The status check in the UPDATE makes the claim safe between workers: a job another worker
    claimed first is skipped.
    """
    candidates = conn.execute(
        select(Job.id).where(Job.status == "queued").order_by(Job.created_at, Job.id).limit(5)
    ).scalars().all()
    for job_id in candidates:
        now = utcnow()
        result = conn.execute(
            update(Job)
            .where(Job.id == job_id, Job.status == "queued")
            .values(status="running", started_at=now, updated_at=now)
        )
        if result.rowcount == 1:
            return get_job(conn=conn, job_id=int(job_id))
    return None


def set_job_progress(*, conn: Connection, job_id: int, progress: float) -> None:
    """Record a running job's progress (clipped to [0, 1])."""
    value = min(max(float(progress), 0.0), 1.0)
    conn.execute(update(Job).where(Job.id == job_id).values(progress=value, updated_at=utcnow()))


def finish_job(*, conn: Connection, job_id: int, session_id: int | None, map_id: int | None) -> None:
    """Mark a job ``done`` with the session and map it produced."""
    now = utcnow()
    conn.execute(
        update(Job)
        .where(Job.id == job_id)
        .values(status="done", progress=1.0, session_id=session_id, map_id=map_id, finished_at=now, updated_at=now)
    )


def set_job_dropped(*, conn: Connection, job_id: int, dropped: Mapping[str, Any]) -> None:
    """Keep what reading the job's log dropped (``IngestReport.as_dict()``) as ``options.dropped``."""
    record = get_job(conn=conn, job_id=job_id)
    options = {**(record.options or {}), "dropped": dict(dropped)}
    conn.execute(update(Job).where(Job.id == job_id).values(options=options, updated_at=utcnow()))


def fail_job(*, conn: Connection, job_id: int, error: str) -> None:
    """Mark a job ``failed`` with a one-line error."""
    now = utcnow()
    line = " ".join(error.split())[:2000]
    conn.execute(
        update(Job).where(Job.id == job_id).values(status="failed", error=line, finished_at=now, updated_at=now)
    )


# --------------------------------------------------------------------------------- job engine support
# Additive functions for the REST API's job engine (issue 6): duplicate detection, per-map claims and
# restart recovery. ``options`` (JSON) carries ``attempts`` (how often a server stop interrupted the job).


def find_upload_job(
    *,
    conn: Connection,
    upload_sha256: str,
    topics: Mapping[str, Any] | None,
    preset: str | None,
    options: Mapping[str, Any] | None = None,
) -> JobRecord | None:
    """Return the newest job, not failed, for the same upload bytes and the same request, or None.

    Same request: same topic overrides, preset, and the given ``options`` entries (e.g. ``merge``, the
    requested map).
    """
    rows = conn.execute(
        select(Job.__table__)
        .where(Job.upload_sha256 == upload_sha256, Job.status != "failed")
        .order_by(Job.id.desc())
    ).all()
    wanted_topics = None if topics is None else dict(topics)
    wanted_options = {k: v for k, v in (options or {}).items() if k != "attempts"}
    for row in rows:
        record = _record(row)
        stored_options = {k: v for k, v in (record.options or {}).items() if k != "attempts"}
        if (record.topics, record.preset) == (wanted_topics, preset) and all(
            stored_options.get(k) == v for k, v in wanted_options.items()
        ):
            return record
    return None


def lock_upload(*, conn: Connection, upload_sha256: str) -> None:
    """Serialise duplicate checks of one upload until commit (PostgreSQL advisory lock; SQLite writers queue)."""
    if conn.dialect.name == "postgresql":
        conn.execute(text("SELECT pg_advisory_xact_lock(hashtext(:key))"), {"key": f"mapserver-upload:{upload_sha256}"})


def claim_next_job_excluding(*, conn: Connection, busy_maps: Collection[str]) -> JobRecord | None:
    """Mark the oldest queued job whose ``map_name`` is not in ``busy_maps`` ``running``; return it (or None).

    Jobs of one map therefore run one after another when the caller passes the maps it is running.
    """
    rows = conn.execute(
        select(Job.id, Job.map_name).where(Job.status == "queued").order_by(Job.created_at, Job.id).limit(200)
    ).all()
    for job_id, map_name in rows:
        if map_name is not None and map_name in busy_maps:
            continue
        now = utcnow()
        result = conn.execute(
            update(Job)
            .where(Job.id == job_id, Job.status == "queued")
            .values(status="running", started_at=now, updated_at=now, progress=0.0)
        )
        if result.rowcount == 1:
            return get_job(conn=conn, job_id=int(job_id))
    return None


def requeue_job(*, conn: Connection, job_id: int, count_attempt: bool = False) -> None:
    """Put a running job back in the queue (progress 0); ``count_attempt`` increments ``options.attempts``."""
    record = get_job(conn=conn, job_id=job_id)
    options = dict(record.options or {})
    if count_attempt:
        options["attempts"] = int(options.get("attempts", 0)) + 1
    conn.execute(
        update(Job)
        .where(Job.id == job_id)
        .values(status="queued", progress=0.0, started_at=None, options=options, updated_at=utcnow())
    )


def recover_interrupted_jobs(*, conn: Connection, max_attempts: int) -> tuple[list[int], list[int]]:
    """After a server start: rerun jobs left ``running`` from the start, or fail those interrupted too often.

    A job whose ``options.attempts`` (interruptions so far, this one included) reaches ``max_attempts``
    is failed with the reason; the others are queued again.

    Returns:
        (ids queued again, ids failed).
    """
    requeued: list[int] = []
    failed: list[int] = []
    running = conn.execute(select(Job.id).where(Job.status == "running").order_by(Job.id)).scalars().all()
    for job_id in running:
        record = get_job(conn=conn, job_id=int(job_id))
        attempts = int((record.options or {}).get("attempts", 0)) + 1
        if attempts >= max_attempts:
            fail_job(
                conn=conn,
                job_id=record.id,
                error=f"the server stopped while this job was running, {attempts} times; giving up (upload it again)",
            )
            failed.append(record.id)
        else:
            requeue_job(conn=conn, job_id=record.id, count_attempt=True)
            requeued.append(record.id)
    return requeued, failed


def count_jobs(*, conn: Connection) -> dict[str, int]:
    """Return the number of jobs per status (every status present, zero when none)."""
    rows = conn.execute(select(Job.status, func.count()).group_by(Job.status)).all()
    counts = dict.fromkeys(JOB_STATUSES, 0)
    counts.update({str(status): int(n) for status, n in rows})
    return counts

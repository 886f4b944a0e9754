"""Processing jobs of the REST API (issue 6): queued uploads, claimed by a worker, progress, outcome.

Fencing: every claim of a job (queued → running) and every takeover by someone other than its holder
(recovery of a job whose holder died) adds one to ``jobs.lease_token``; the claimer gets the new value in
its :class:`JobRecord`. Every later write of the holder — progress, lease renewal, outcome, giving the job
back — is an ``UPDATE ... WHERE id = ? AND lease_token = ? AND status = 'running'`` and returns whether a
row changed, so a holder that lost the job writes nothing and learns that it should stop.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import ColumnElement, Connection, func, insert, or_, select, text, update

from mapserver.errors import NotFoundError
from mapserver.store.models import JOB_STATUSES, Job, Session, utcnow


@dataclass(frozen=True, slots=True)
class JobRecord:
    """A stored job (``status``: queued, running, done or failed; ``progress`` in [0, 1]).

    ``lease_token``: the job's fencing token as read (see the module docstring); a claimed record carries
    the value its holder must present with every write.
    """

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
    lease_token: int = 0


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
        lease_token=int(row.lease_token),
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


def _claim_values(owner: str | None, lease_s: float | None) -> dict[str, Any]:
    """Return the column values of a claim: running, a new fencing token, the holder and its lease."""
    now = utcnow()
    expires = None if lease_s is None else now + timedelta(seconds=lease_s)
    return {"status": "running", "started_at": now, "updated_at": now, "progress": 0.0,
            "lease_token": Job.lease_token + 1, "lease_owner": owner, "lease_expires_at": expires}  # fmt: skip


def _held(job_id: int, lease_token: int) -> tuple[ColumnElement[bool], ...]:
    """Return the WHERE clause of a holder's write: this job, still running, still at the holder's token."""
    return (Job.id == job_id, Job.lease_token == lease_token, Job.status == "running")


def claim_next_job(*, conn: Connection, owner: str | None = None, lease_s: float | None = None) -> JobRecord | None:
    """Mark the oldest queued job ``running`` (a new fencing token) and return it (None when the queue is empty).

    The status check in the UPDATE makes the claim safe between workers: a job another worker
    claimed first is skipped.
    """
    candidates = conn.execute(
        select(Job.id).where(Job.status == "queued").order_by(Job.created_at, Job.id).limit(5)
    ).scalars().all()
    for job_id in candidates:
        result = conn.execute(
            update(Job).where(Job.id == job_id, Job.status == "queued").values(**_claim_values(owner, lease_s))
        )
        if result.rowcount == 1:
            return get_job(conn=conn, job_id=int(job_id))
    return None


def set_job_progress(*, conn: Connection, job_id: int, progress: float, lease_token: int) -> bool:
    """Record a running job's progress (clipped to [0, 1]); return False when ``lease_token`` no longer holds it."""
    value = min(max(float(progress), 0.0), 1.0)
    result = conn.execute(update(Job).where(*_held(job_id, lease_token)).values(progress=value, updated_at=utcnow()))
    return result.rowcount == 1


def finish_job(*, conn: Connection, job_id: int, session_id: int | None, map_id: int | None, lease_token: int) -> bool:
    """Mark a job ``done`` with the session and map it produced, if ``lease_token`` still holds it; return that."""
    now = utcnow()
    result = conn.execute(
        update(Job)
        .where(*_held(job_id, lease_token))
        .values(status="done", progress=1.0, session_id=session_id, map_id=map_id, finished_at=now, updated_at=now,
                lease_expires_at=None)
    )  # fmt: skip
    return result.rowcount == 1


def set_job_dropped(*, conn: Connection, job_id: int, dropped: Mapping[str, Any]) -> None:
    """Keep what reading the job's log dropped (``IngestReport.as_dict()``) as ``options.dropped``."""
    record = get_job(conn=conn, job_id=job_id)
    options = {**(record.options or {}), "dropped": dict(dropped)}
    conn.execute(update(Job).where(Job.id == job_id).values(options=options, updated_at=utcnow()))


def one_line(error: str) -> str:
    """Return ``error`` on one line, at most 2000 characters (how job errors are stored)."""
    return " ".join(error.split())[:2000]


def fail_job(*, conn: Connection, job_id: int, error: str, lease_token: int) -> bool:
    """Mark a job ``failed`` with a one-line error, if ``lease_token`` still holds it; return that."""
    now = utcnow()
    result = conn.execute(
        update(Job)
        .where(*_held(job_id, lease_token))
        .values(status="failed", error=one_line(error), finished_at=now, updated_at=now, lease_expires_at=None)
    )
    return result.rowcount == 1


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


def claim_next_job_excluding(
    *, conn: Connection, busy_maps: Collection[str], owner: str | None = None, lease_s: float | None = None
) -> JobRecord | None:
    """Mark the oldest queued job whose ``map_name`` is not in ``busy_maps`` ``running``; return it (or None).

    Jobs of one map therefore run one after another when the caller passes the maps it is running. The
    claim takes a new fencing token and leases the job to ``owner`` for ``lease_s`` seconds.
    """
    rows = conn.execute(
        select(Job.id, Job.map_name).where(Job.status == "queued").order_by(Job.created_at, Job.id).limit(200)
    ).all()
    for job_id, map_name in rows:
        if map_name is not None and map_name in busy_maps:
            continue
        result = conn.execute(
            update(Job).where(Job.id == job_id, Job.status == "queued").values(**_claim_values(owner, lease_s))
        )
        if result.rowcount == 1:
            return get_job(conn=conn, job_id=int(job_id))
    return None


def requeue_job(*, conn: Connection, job_id: int, lease_token: int, count_attempt: bool = False) -> bool:
    """Give a running job back to the queue (progress 0) if ``lease_token`` still holds it; return that.

    ``count_attempt`` increments ``options.attempts``.
    """
    record = get_job(conn=conn, job_id=job_id)
    options = dict(record.options or {})
    if count_attempt:
        options["attempts"] = int(options.get("attempts", 0)) + 1
    result = conn.execute(
        update(Job)
        .where(*_held(job_id, lease_token))
        .values(status="queued", progress=0.0, started_at=None, options=options, updated_at=utcnow(),
                lease_owner=None, lease_expires_at=None)
    )  # fmt: skip
    return result.rowcount == 1


def renew_job_leases(*, conn: Connection, leases: Mapping[int, int], lease_s: float) -> list[int]:
    """Push the leases of running jobs (job id → fencing token) ``lease_s`` seconds ahead; return the ids lost.

    A job is lost when its token or status changed: someone else took it over or finished it.
    """
    expires = utcnow() + timedelta(seconds=lease_s)
    lost = []
    for job_id, token in sorted(leases.items()):
        result = conn.execute(update(Job).where(*_held(job_id, token)).values(lease_expires_at=expires))
        if result.rowcount != 1:
            lost.append(job_id)
    return lost


def recover_interrupted_jobs(
    *, conn: Connection, max_attempts: int, expired_only: bool = False
) -> tuple[list[int], list[int]]:
    """Take over jobs left ``running`` by a holder that is gone: queue them again, or fail those interrupted too often.

    ``expired_only``: only jobs whose lease expired (or that have none); otherwise every running job — for
    a caller that knows no other job engine runs on this database. A job whose ``options.attempts``
    (interruptions so far, this one included) reaches ``max_attempts`` is failed with the reason; the others
    are queued again. Each takeover adds one to the job's fencing token, so the old holder, should it still
    run, writes nothing more.

    Returns:
        (ids queued again, ids failed).
    """
    query = select(Job.id, Job.lease_token, Job.options).where(Job.status == "running").order_by(Job.id)
    if expired_only:
        query = query.where(or_(Job.lease_expires_at.is_(None), Job.lease_expires_at < utcnow()))
    requeued: list[int] = []
    failed: list[int] = []
    for job_id, token, stored in conn.execute(query).all():
        options = dict(stored or {})
        options["attempts"] = attempts = int(options.get("attempts", 0)) + 1
        now = utcnow()
        values: dict[str, Any] = {"options": options, "updated_at": now, "lease_token": token + 1,
                                  "lease_owner": None, "lease_expires_at": None}  # fmt: skip
        if attempts >= max_attempts:
            msg = f"the server stopped while this job was running, {attempts} times; giving up (upload it again)"
            values.update(status="failed", error=msg, finished_at=now)
        else:
            values.update(status="queued", progress=0.0, started_at=None)
        if conn.execute(update(Job).where(*_held(int(job_id), int(token))).values(**values)).rowcount == 1:
            (failed if attempts >= max_attempts else requeued).append(int(job_id))
    return requeued, failed


def job_uploads(
    *, conn: Connection, statuses: Collection[str] | None = None, finished_before: datetime | None = None
) -> list[tuple[int, str, str]]:
    """Return (id, status, upload path) of the jobs with one of ``statuses`` (None: any), in id order.

    ``finished_before``: only jobs that finished (done or failed) before this time.
    """
    query = select(Job.id, Job.status, Job.upload_path).order_by(Job.id)
    if statuses is not None:
        query = query.where(Job.status.in_(tuple(statuses)))
    if finished_before is not None:
        query = query.where(Job.finished_at.is_not(None), Job.finished_at < finished_before)
    return [(int(i), str(status), str(path)) for i, status, path in conn.execute(query).all()]


def page_jobs(
    *, conn: Connection, status: str | None = None, map_id: int | None = None, map_name: str | None = None,
    before: int | None = None, limit: int = 50,
) -> tuple[list[JobRecord], int, bool]:  # fmt: skip
    """Return one page of jobs, newest first, how many match the filters in all, and whether older ones follow.

    Args:
        conn: the store's connection.
        status: only jobs of this status.
        map_id: with ``map_name``: only jobs that stored into that map or asked for that name (either).
        map_name: see ``map_id`` (a name with no map id: only jobs that asked for it).
        before: only jobs with a smaller id (the keyset of the next page: the last id of this one).
        limit: page size.
    """
    filters: list[ColumnElement[bool]] = []
    if status is not None:
        filters.append(Job.status == status)
    if map_name is not None:
        filters.append(or_(Job.map_name == map_name, Job.map_id == map_id) if map_id is not None
                       else Job.map_name == map_name)  # fmt: skip
    total = int(conn.execute(select(func.count()).select_from(Job).where(*filters)).scalar_one())
    if before is not None:
        filters.append(Job.id < before)
    rows = conn.execute(select(Job.__table__).where(*filters).order_by(Job.id.desc()).limit(limit + 1)).all()
    return [_record(row) for row in rows[:limit]], total, len(rows) > limit


def count_jobs(*, conn: Connection) -> dict[str, int]:
    """Return the number of jobs per status (every status present, zero when none)."""
    rows = conn.execute(select(Job.status, func.count()).group_by(Job.status)).all()
    counts = dict.fromkeys(JOB_STATUSES, 0)
    counts.update({str(status): int(n) for status, n in rows})
    return counts


def last_done_upload(*, conn: Connection, session_name: str) -> str | None:
    """Return the upload path of the newest done job that stored session ``session_name`` (None: none, or no path)."""
    row = conn.execute(
        select(Job.upload_path).join(Session, Session.id == Job.session_id)
        .where(Session.name == session_name, Job.status == "done").order_by(Job.id.desc())
    ).first()  # fmt: skip
    return None if row is None or not row[0] else str(row[0])


def done_job_runs(*, conn: Connection) -> list[tuple[datetime, datetime, dict[str, Any] | None]]:
    """Return ``(started_at, finished_at, options)`` of every done job with both times, by finish time then id."""
    rows = conn.execute(
        select(Job.started_at, Job.finished_at, Job.options)
        .where(Job.status == "done", Job.started_at.is_not(None), Job.finished_at.is_not(None))
        .order_by(Job.finished_at, Job.id)
    ).all()
    return [(r[0], r[1], r[2]) for r in rows]

"""Job leases and per-map locks for distributed workers (issue 15); PostgreSQL only.

The ``jobs`` table stays the source of truth. A distributed worker runs the jobs of one map at a time
(``map key`` = ``jobs.map_name``, or ``#job-<id>`` for a job without one) while it holds that map's
PostgreSQL session-level advisory lock (:class:`MapLock`). Holding the lock, it claims the oldest
unfinished job of the map (:func:`claim_map_job`): a queued one, or a ``running`` one — which, since
no one else holds the lock, lost its worker (killed, machine gone: the database dropped the dead
connection and with it the lock) and is taken over (``options.attempts`` + 1; failed after
``max_attempts``). Every claim and takeover adds one to the job's fencing token (``jobs.lease_token``,
see :mod:`mapserver.store.jobs`). While it runs, a heartbeat pushes ``lease_expires_at`` forward
(:func:`renew_lease`); the outcome is written only by the lease owner at its token (:func:`complete_job`).

Queued jobs are *dispatched* (a message naming their map is sent to the workers) by
:func:`due_job_maps`, which also marks them (``lease_expires_at`` = when to dispatch again), so a
lost message or a crashed sender only delays a job; a running job whose lease expired has its map
dispatched again too. Duplicate messages are harmless: a worker that cannot take the map's lock, or
finds nothing to claim, does nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import timedelta

from sqlalchemy import ColumnElement, Connection, and_, func, or_, select, text, update

from mapserver.store.db import Database
from mapserver.store.jobs import JobRecord, get_job, one_line
from mapserver.store.models import Job, utcnow

MAP_LOCK_NAMESPACE = 0x6D61_7073  # "maps": first key of the two-key advisory locks of map jobs
"""Two-key advisory locks live apart from the one-key locks of uploads and the atlas."""


class MapLock:
    """A PostgreSQL session-level advisory lock on one map key, held on a dedicated connection.

    The lock lives as long as the connection: a worker killed with ``kill -9`` loses its connection
    and the database releases the lock at once.
    """

    def __init__(self, db: Database, key: str) -> None:
        self.db = db
        self.key = key
        self._conn: Connection | None = None

    def try_acquire(self) -> bool:
        """Take the lock without waiting; return whether this process holds it now."""
        conn = self.db.engine.connect().execution_options(isolation_level="AUTOCOMMIT")
        got = conn.execute(
            text("SELECT pg_try_advisory_lock(:ns, hashtext(:key))"), {"ns": MAP_LOCK_NAMESPACE, "key": self.key}
        ).scalar_one()
        if not got:
            conn.close()
            return False
        self._conn = conn
        return True

    def alive(self) -> bool:
        """Return whether the connection holding the lock still answers (False: the lock may be lost)."""
        if self._conn is None:
            return False
        try:
            self._conn.execute(text("SELECT 1"))
        except Exception:  # any driver error: the session, and with it the lock, is gone
            return False
        return True

    def release(self) -> None:
        """Release the lock (idempotent); closing the connection would release it too."""
        if self._conn is None:
            return
        try:
            self._conn.execute(
                text("SELECT pg_advisory_unlock(:ns, hashtext(:key))"), {"ns": MAP_LOCK_NAMESPACE, "key": self.key}
            )
        except Exception:
            pass
        finally:
            self._conn.close()
            self._conn = None


def _key_filter(key: str):
    if key.startswith("#job-") and key[5:].isdigit():
        return and_(Job.id == int(key[5:]), Job.map_name.is_(None))
    return Job.map_name == key


@dataclass(frozen=True, slots=True)
class Claim:
    """The outcome of :func:`claim_map_job`: the job now leased (or None) and jobs failed on the way."""

    job: JobRecord | None
    failed: tuple[int, ...] = ()
    taken_over: bool = False


def claim_map_job(*, conn: Connection, key: str, owner: str, lease_s: float, max_attempts: int) -> Claim:
    """Lease the oldest unfinished job of a map to ``owner``; call it only while holding the map's lock.

    A ``running`` job found here lost its worker (its lock is free): it is taken over with
    ``options.attempts`` + 1, or failed with the reason once that reaches ``max_attempts``. Both, and the
    claim, add one to the job's fencing token.
    """
    failed: list[int] = []
    while True:
        row = conn.execute(
            select(Job.id, Job.status)
            .where(_key_filter(key), Job.status.in_(("queued", "running")))
            .order_by(Job.created_at, Job.id)
            .limit(1)
        ).first()
        if row is None:
            return Claim(None, tuple(failed))
        record = get_job(conn=conn, job_id=int(row.id))
        options = dict(record.options or {})
        taken_over = row.status == "running"
        if taken_over:
            options["attempts"] = int(options.get("attempts", 0)) + 1
            if options["attempts"] >= max_attempts:
                msg = f"the worker running this job was lost {options['attempts']} times; giving up (upload it again)"
                now = utcnow()
                conn.execute(
                    update(Job)
                    .where(Job.id == record.id)
                    .values(status="failed", error=msg, finished_at=now, updated_at=now, options=options,
                            lease_owner=None, lease_expires_at=None, lease_token=Job.lease_token + 1)
                )  # fmt: skip
                failed.append(record.id)
                continue
        now = utcnow()
        conn.execute(
            update(Job)
            .where(Job.id == record.id)
            .values(status="running", progress=0.0, started_at=now, updated_at=now, options=options,
                    lease_owner=owner, lease_expires_at=now + timedelta(seconds=lease_s),
                    lease_token=Job.lease_token + 1)
        )  # fmt: skip
        return Claim(get_job(conn=conn, job_id=record.id), tuple(failed), taken_over)


def _held(job_id: int, owner: str, lease_token: int) -> tuple[ColumnElement[bool], ...]:
    return (Job.id == job_id, Job.status == "running", Job.lease_owner == owner, Job.lease_token == lease_token)


def renew_lease(*, conn: Connection, job_id: int, owner: str, lease_s: float, lease_token: int) -> bool:
    """Push a running job's lease ``lease_s`` seconds ahead; return False when ``owner`` at ``lease_token`` lost it."""
    now = utcnow()
    result = conn.execute(
        update(Job).where(*_held(job_id, owner, lease_token)).values(lease_expires_at=now + timedelta(seconds=lease_s))
    )
    return result.rowcount == 1


def complete_job(
    *, conn: Connection, job_id: int, owner: str, lease_token: int, session_id: int | None, map_id: int | None,
    error: str | None,
) -> bool:
    """Record a leased job's outcome (done, or failed with ``error``) if ``owner`` still holds it at ``lease_token``."""
    now = utcnow()
    values: dict[str, object] = {"finished_at": now, "updated_at": now, "lease_expires_at": None}
    if error is None:
        values.update(status="done", progress=1.0, session_id=session_id, map_id=map_id)
    else:
        values.update(status="failed", error=one_line(error))
    result = conn.execute(update(Job).where(*_held(job_id, owner, lease_token)).values(**values))
    return result.rowcount == 1


def due_job_maps(*, conn: Connection, redispatch_s: float) -> list[str]:
    """Return the map keys whose jobs need a message now, marking their queued jobs as dispatched.

    Due: queued jobs never dispatched or dispatched more than ``redispatch_s`` ago (their
    ``lease_expires_at`` is moved that far ahead, in the same UPDATE, so concurrent dispatchers
    send one message per job and window), and running jobs whose lease expired (their worker is
    gone; the worker that takes the map's lock takes them over).
    """
    now = utcnow()
    queued = conn.execute(
        update(Job)
        .where(Job.status == "queued", or_(Job.lease_expires_at.is_(None), Job.lease_expires_at < now))
        .values(lease_expires_at=now + timedelta(seconds=redispatch_s))
        .returning(Job.id, Job.map_name)
    ).all()
    lost = conn.execute(
        select(Job.id, Job.map_name).where(Job.status == "running", Job.lease_expires_at < now)
    ).all()
    keys: dict[str, None] = {}
    for job_id, name in sorted([*queued, *lost]):
        keys[name if name is not None else f"#job-{job_id}"] = None
    return list(keys)


def has_unfinished(*, conn: Connection, key: str) -> bool:
    """Return whether the map has a queued or running job."""
    count = conn.execute(
        select(func.count()).select_from(Job).where(_key_filter(key), Job.status.in_(("queued", "running")))
    ).scalar_one()
    return int(count) > 0

"""Upload admission: the reasons a queued job would fail that are known when the log is uploaded.

The REST API asks :func:`admission_conflict` before it answers 202, inside the write transaction that
queues the job and after :func:`lock_admission`, so two uploads are decided one after the other: of two
concurrent uploads of one log under different map names, or of two logs asking for one new map name,
the first is queued and the second is refused (409), never both queued with one failing at the end.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from sqlalchemy import Connection, func, select

from mapserver.errors import ConflictError, MapServerError
from mapserver.store.errors import UnknownMapError
from mapserver.store.models import Job, Map, Session
from mapserver.store.sessions import find_session

ADMISSION_LOCK_KEY = 0x75706C64  # "upld"
"""PostgreSQL advisory lock taken by :func:`lock_admission`."""

PENDING = ("queued", "running")


@dataclass(frozen=True, slots=True)
class UploadClaim:
    """What an upload asks for.

    Attributes:
        upload_sha256: SHA-256 of the uploaded bytes.
        topics: the topic overrides as the job stores them (None: none).
        map_name: the new map's name the request gives (None: the log's name, made unique when it runs).
        log_sha256: the log's identity (SHA-256 of its file or bag directory), None before it is known.
        mapping: the topic mapping processing will use, None before it is known.
        into: the existing map the session must merge into (None: none named).
    """

    upload_sha256: str
    topics: Mapping[str, Any] | None
    map_name: str | None
    log_sha256: str | None = None
    mapping: Mapping[str, Any] | None = None
    into: str | None = None


def lock_admission(*, conn: Connection) -> None:
    """Serialise admission decisions until this transaction ends.

    SQLite write transactions hold the database write lock already (``BEGIN IMMEDIATE``); on PostgreSQL a
    transaction-level advisory lock makes a second decision wait until the first one's job is committed.
    """
    if conn.dialect.name == "postgresql":
        conn.execute(select(func.pg_advisory_xact_lock(ADMISSION_LOCK_KEY)))


def admission_refusal(*, conn: Connection, claim: UploadClaim) -> MapServerError | None:
    """Return the error the upload is refused with (404 or 409), or None when it can be queued.

    With ``into``: :func:`into_refusal`; otherwise :func:`admission_conflict` as a 409.
    """
    if claim.into is not None:
        return into_refusal(conn=conn, claim=claim)
    reason = admission_conflict(conn=conn, claim=claim)
    return None if reason is None else ConflictError(reason)


def into_refusal(*, conn: Connection, claim: UploadClaim) -> MapServerError | None:
    """Return why an upload sent into an existing map cannot be queued, or None.

    404: no map of that name. 409: another pending job processes the same bytes; the map is archived; one of
    its sessions is partial (still being processed: no merge candidate); and, once the log's identity is
    known, the log is stored already in another map. A log stored in that map already passes (its job
    answers with the stored session).
    """
    busy = _pending_same_upload(conn, claim)
    if busy is not None:
        return ConflictError(busy)
    into = str(claim.into)
    row = conn.execute(select(Map.id, Map.archived_at).where(Map.name == into)).first()
    if row is None:
        return UnknownMapError(f"no map named {into!r} to merge into")
    if row[1] is not None:
        return ConflictError(f"map {into!r} is archived (deleted); restore it before sending sessions into it")
    session = None
    if claim.log_sha256 is not None and claim.mapping is not None:
        session = find_session(conn=conn, log_sha256=claim.log_sha256, topics=claim.mapping)
    if session is not None and session.map_id is not None:
        if session.map_id == row[0]:
            return None
        home = conn.execute(select(Map.name).where(Map.id == session.map_id)).scalar_one_or_none()
        return ConflictError(
            f"this log is stored already as session {session.name!r} of map {home!r}; it cannot merge into "
            f"map {into!r}"
        )
    partial = conn.execute(
        select(Session.name).where(Session.map_id == row[0], Session.status == "partial").order_by(Session.id)
    ).scalars().first()
    if partial is not None:
        return ConflictError(
            f"session {partial!r} of map {into!r} is still being processed (partial); send sessions into the "
            "map when it is complete"
        )
    return None


def admission_conflict(*, conn: Connection, claim: UploadClaim) -> str | None:
    """Return why the upload's job would fail (one line), or None when it can be queued.

    Checked: another pending job processes the same bytes with the same topics; a pending job creates a
    map of the name asked for; and, once the log's identity is known (``log_sha256`` and ``mapping``), the
    log is stored already in an archived map or in another map than the one named, or the named map
    exists (live or archived) and the log is not one of its sessions.
    """
    busy = _pending_same_upload(conn, claim)
    if busy is not None:
        return busy
    if claim.map_name is None:
        return _stored_in_archived_map(conn, claim)
    wanted = claim.map_name
    creator = pending_map_creator(conn=conn, name=wanted)
    if creator is not None:
        return f"job {creator} is creating a map named {wanted!r}; choose another map name"
    held = conn.execute(select(Map.archived_at).where(Map.name == wanted)).first()
    if held is not None and held[0] is not None:
        return f"the name {wanted!r} is held by an archived (deleted) map; restore or purge it, or choose another"
    if claim.log_sha256 is None or claim.mapping is None:
        return None
    session = find_session(conn=conn, log_sha256=claim.log_sha256, topics=claim.mapping)
    target = conn.execute(select(Map.id).where(Map.name == wanted)).scalar_one_or_none()
    if session is not None and session.map_id is not None and session.map_id != target:
        home = conn.execute(select(Map.name).where(Map.id == session.map_id)).scalar_one_or_none()
        return (
            f"this log is stored already as session {session.name!r} of map {home!r}; "
            f"it cannot go into map {wanted!r}"
        )
    if target is not None and (session is None or session.map_id != target):
        return (
            f"a map named {wanted!r} exists already and this log is not one of its sessions; "
            "choose another map name"
        )
    return None


def _stored_in_archived_map(conn: Connection, claim: UploadClaim) -> str | None:
    """Return the refusal when the log is a session of an archived map (processing it would need the map)."""
    if claim.log_sha256 is None or claim.mapping is None:
        return None
    session = find_session(conn=conn, log_sha256=claim.log_sha256, topics=claim.mapping)
    if session is None or session.map_id is None:
        return None
    row = conn.execute(select(Map.name, Map.archived_at).where(Map.id == session.map_id)).first()
    if row is None or row[1] is None:
        return None
    return f"this log is stored already as session {session.name!r} of map {row[0]!r}, which is archived; restore it"


def _pending_same_upload(conn: Connection, claim: UploadClaim) -> str | None:
    """Return the refusal when a pending job processes the same bytes with the same topic overrides."""
    rows = conn.execute(
        select(Job.id, Job.topics, Job.map_name)
        .where(Job.upload_sha256 == claim.upload_sha256, Job.status.in_(PENDING))
        .order_by(Job.id)
    ).all()
    wanted = None if claim.topics is None else dict(claim.topics)
    for job_id, topics, map_name in rows:
        if topics == wanted:
            return (
                f"this log is being processed by job {int(job_id)} (map {map_name!r}); follow that job, or upload "
                "the log again when it is done"
            )
    return None


def pending_map_creator(*, conn: Connection, name: str, except_job: int | None = None) -> int | None:
    """Return the id of a pending job that creates, or may create, a map called ``name`` (None: none does).

    That is a queued or running job whose request names the map, or a running job whose map is named
    after its log (it chose the name when it started). ``except_job`` is left out (a job asking for itself).
    """
    rows = conn.execute(
        select(Job.id, Job.status, Job.options).where(Job.map_name == name, Job.status.in_(PENDING)).order_by(Job.id)
    ).all()
    for job_id, status, options in rows:
        if int(job_id) != except_job and ((options or {}).get("map_given") or status == "running"):
            return int(job_id)
    return None

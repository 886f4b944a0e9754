"""``GET /v1/jobs``: the jobs, newest first, a page at a time; ``GET /v1/jobs/{job}``: the state of one."""

from __future__ import annotations

import contextlib
from typing import Annotated, Any

from fastapi import APIRouter, Path, Query

from mapserver.api.deps import ReadAccess, ServicesDep
from mapserver.api.schemas import ErrorPublic, JobPublic, JobsPublic, JobStatus
from mapserver.errors import NotFoundError
from mapserver.store import Connection, get_map, get_map_by_id, get_session
from mapserver.store.jobs import JobRecord, get_job, page_jobs
from mapserver.store.sessions import SessionRecord

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorPublic}, 403: {"model": ErrorPublic}, 404: {"model": ErrorPublic}
}
MAX_ID = 2**62


def job_public(conn: Connection, job: JobRecord) -> JobPublic:
    """Return the public view of a job (session and map by name)."""
    session: SessionRecord | None = None
    if job.session_id is not None:
        try:
            session = get_session(conn=conn, session_id=job.session_id)
        except NotFoundError:
            session = None
    map_name = job.map_name
    map_id = job.map_id if job.map_id is not None else (session.map_id if session is not None else None)
    if session is not None and session.map_id is not None:
        map_id = session.map_id  # the session's map now (a later merge may have joined it into another)
    if map_id is not None:
        with contextlib.suppress(NotFoundError):
            map_name = get_map_by_id(conn=conn, map_id=map_id).name
    return JobPublic(
        job=job.id,
        status=job.status,
        progress=job.progress,
        error=job.error,
        session=None if session is None else session.name,
        map=map_name,
        upload=job.upload_name,
        preset=job.preset,
        created_at=job.created_at,
        started_at=job.started_at,
        finished_at=job.finished_at,
        dropped=(job.options or {}).get("dropped"),
    )


MAX_JOBS_PAGE = 100


@router.get("", operation_id="list_jobs", response_model=JobsPublic, responses={**ERRORS, 422: {"model": ErrorPublic}})
def read_jobs(
    services: ServicesDep,
    _token: ReadAccess,
    status: Annotated[JobStatus | None, Query(description="only jobs of this status")] = None,
    map: Annotated[
        str | None, Query(min_length=1, max_length=200, description="only jobs that asked for or stored into this map")
    ] = None,
    before: Annotated[int | None, Query(ge=1, le=MAX_ID, description="only jobs older than this id (paging)")] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_JOBS_PAGE, description="page size")] = 50,
) -> JobsPublic:
    """Return the jobs, newest first (sent by anyone: the viewer, curl, another server's clients), a page at a time."""
    with services.db.read() as conn:
        map_id = None
        if map is not None:
            with contextlib.suppress(NotFoundError):
                map_id = get_map(conn=conn, name=map).id
        records, total, more = page_jobs(conn=conn, status=status, map_id=map_id, map_name=map, before=before,
                                         limit=limit)  # fmt: skip
        jobs = [job_public(conn, record) for record in records]
    return JobsPublic(jobs=jobs, total=total, next=records[-1].id if more else None)


@router.get("/{job}", operation_id="get_job", response_model=JobPublic, responses=ERRORS)
def read_job(job: Annotated[int, Path(ge=1, le=MAX_ID)], services: ServicesDep, _token: ReadAccess) -> JobPublic:
    """Return a job's status, progress (fraction of frames done), error, session and map."""
    with services.db.read() as conn:
        return job_public(conn, get_job(conn=conn, job_id=job))

"""``POST /v1/sessions``: upload a mission log; it is checked, stored and queued for processing."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path, Query, Request
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

from mapserver.api.deps import ServicesDep, WriteAccess
from mapserver.api.errors import raise_server_fault
from mapserver.api.intake import StoredLog, parse_options, store_log
from mapserver.api.schemas import ErrorPublic, UploadAccepted
from mapserver.api.uploads import FILE_FIELD, receive_upload
from mapserver.atlas.undo import move_session
from mapserver.store import get_session
from mapserver.store.jobs import JobRecord

router = APIRouter(prefix="/v1/sessions", tags=["sessions"])

UPLOAD_BODY: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": [FILE_FIELD],
                    "properties": {
                        FILE_FIELD: {
                            "type": "string",
                            "format": "binary",
                            "description": "a .bag, .db3 or .mcap file, or a ROS 2 bag directory as .zip/.tar(.gz)",
                        },
                        "preset": {"type": "string", "description": "engine preset (default circle)"},
                        "map": {"type": "string", "description": "name of the new map if it joins none"},
                        "into": {"type": "string", "description": "an existing map the session must merge into "
                                 "(instead of map); the job fails, storing nothing, if it does not merge"},
                        "topics": {"type": "string", "description": "topic overrides: image=/cam,odometry=/odom"},
                        "merge": {"type": "string", "enum": ["true", "false"], "description": "default true"},
                    },
                }
            }
        },
    }
}
ERRORS: dict[int | str, dict[str, Any]] = {
    code: {"model": ErrorPublic} for code in (400, 401, 403, 404, 408, 409, 413, 415, 422, 507)
}


def _session_name(services: ServicesDep, job: JobRecord) -> str | None:
    if job.session_id is None:
        return None
    with services.db.read() as conn:
        return get_session(conn=conn, session_id=job.session_id).name


@router.post(
    "",
    operation_id="upload_session",
    status_code=202,
    response_model=UploadAccepted,
    responses=ERRORS,
    openapi_extra=UPLOAD_BODY,
)
async def upload_session(request: Request, services: ServicesDep, _token: WriteAccess) -> JSONResponse:
    """Store an uploaded log and queue its processing; answer 202 with the job.

    The upload is streamed to disk and hashed; the same log uploaded again with the same request is
    answered with the earlier job (``duplicate: true``) instead of being queued twice. 409 when the job
    would fail for a reason known now: another pending job processes the same log, or creates the map
    named; the log is stored in another map; the named map exists and the log is not one of its sessions.
    With ``into``: 404 when no map has that name, 409 when it is archived, has a partial session or
    parameters the preset cannot merge with, or the log is stored in another map.
    A full disk while receiving or unpacking is answered 507 (:func:`mapserver.api.errors.raise_server_fault`).
    """
    settings = services.settings
    staging = settings.uploads / ".incoming"
    try:
        received = await receive_upload(
            request, staging=staging, max_bytes=settings.max_upload_bytes, read_timeout_s=settings.read_timeout_s,
            max_trailing_bytes=settings.max_trailing_bytes,
        )
    except Exception as err:
        raise_server_fault(err, doing="receiving an upload", where=staging)
        raise
    stored: StoredLog | None = None
    try:
        options = parse_options(received.fields)
        job = await run_in_threadpool(services.find_duplicate, received, options)
        duplicate = job is not None
        if job is None:
            await run_in_threadpool(services.check_admission, received, options)
            stored = await run_in_threadpool(
                store_log, received, uploads_dir=settings.uploads, topics=options.topics,
                limits=settings.archive_limits,
            )  # fmt: skip
            job, duplicate = await run_in_threadpool(
                services.queue_job, received, stored, options, getattr(request.state, "request_id", None)
            )
    except BaseException as err:
        received.discard()
        if stored is not None:
            stored.discard()
        raise_server_fault(err, doing="storing an upload", where=settings.uploads)
        raise
    received.discard()
    if duplicate and stored is not None:
        stored.discard()
    if not duplicate:
        services.jobs.notify()
    assert job is not None  # a duplicate's, or the one queue_job made
    session = await run_in_threadpool(_session_name, services, job)
    body = UploadAccepted(
        job=job.id,
        session=session,
        status=job.status,
        duplicate=duplicate,
        sha256=received.sha256,
        frames=(job.options or {}).get("frames"),
        map=job.map_name,
    )
    return JSONResponse(body.model_dump(mode="json"), status_code=202)


MOVE_ERRORS: dict[int | str, dict[str, Any]] = {code: {"model": ErrorPublic} for code in (400, 401, 403, 404, 409)}


@router.post("/{name}/move", operation_id="move_session", responses=MOVE_ERRORS)
async def move(
    name: Annotated[str, Path(min_length=1, max_length=200, description="the session's name")],
    services: ServicesDep,
    _token: WriteAccess,
    to: Annotated[str | None, Query(min_length=1, max_length=200, description="the new map's name")] = None,
) -> dict[str, Any]:
    """Take a session out of its merged map into a new map of its own (``mapserver session move``).

    It undoes the merge event that brought the session in; the rest of the map stays whole under its name.
    Answers ``{"moved", "session", "map", "rest", "event", "frames"}``; 400 an invalid name, 404 no such
    session, 409 the name is taken, the session is alone in its map, or its part is entangled with others'.
    """
    outcome = await run_in_threadpool(move_session, services.db, session=name, map_name=to)
    return {"moved": True, "session": outcome.session, "map": outcome.map, "rest": outcome.rest,
            "event": outcome.event_id, "frames": outcome.frames}  # fmt: skip

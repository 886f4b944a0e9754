"""Pydantic schemas of the REST API (one family per resource); the contract is ``interfaces.md``."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, Field

from mapserver.statuses import MergeStatus

JobStatus = Literal["queued", "running", "done", "failed"]


class ErrorPublic(BaseModel):
    """Every error: one line saying what went wrong (a refusal by a limit also names the limit)."""

    detail: str
    limit: str | None = Field(None, description="the limit that refused the request (a key of GET /v1/limits)")


class OdometryRulesPublic(BaseModel):
    """The fixed bounds odometry must keep (``mapserver.bounds``): beyond them a message is dropped."""

    max_position_m: float = Field(description="|x|, |y|, |z| of a pose")
    max_speed_m_s: float = Field(description="speed of a twist, and of a frame's motion over its dt")
    max_yaw_rate_rad_s: float = Field(description="yaw rate of a twist")
    max_bad_fraction: float = Field(
        description="a log is refused when more than this fraction of its odometry messages, or of its frames' "
        "motions, is dropped"
    )


class ValueBoundsPublic(BaseModel):
    """The fixed bounds of imported and queried numbers (``mapserver.bounds``): beyond them the input is refused."""

    max_position_m: float = Field(description="|x|, |y|, |z| of an imported pose, and an imported link's length")
    max_angle_rad: float = Field(description="|angle| of an imported heading or link turn")
    max_time_s: float = Field(description="an imported stamp or duration (durations also at least 0)")
    max_query_coordinate_m: float = Field(description="|value| of a coordinate in a query (nearest point, bbox)")


class LimitsPublic(BaseModel):
    """``GET /v1/limits``: what the server accepts (``serve`` flags of the same names, dashes for underscores)."""

    max_upload_bytes: int = Field(description="largest upload (413 beyond)")
    max_unpacked_bytes: int = Field(description="most bytes one archive may unpack to")
    max_unpacked_ratio: float = Field(description="an archive may unpack to at most this multiple of its own size")
    max_archive_entries: int = Field(description="most entries (files and directories) in one archive")
    max_image_pixels: int = Field(description="most pixels (width × height) of one camera frame")
    max_trailing_bytes: int = Field(description="most bytes an upload may send after its closing boundary (400)")
    max_exports: int = Field(description="most map exports at once (503 with Retry-After beyond)")
    read_timeout_s: float = Field(description="an upload that sends nothing this long is answered 408")
    odometry: OdometryRulesPublic
    values: ValueBoundsPublic


class HealthPublic(BaseModel):
    """``GET /healthz`` (``engine``, ``broker``, ``queue`` and ``workers`` only in distributed mode)."""

    status: Literal["ok"] = "ok"
    engine: str | None = None
    broker: str | None = Field(None, description="'ok' or 'unreachable: reason'")
    queue: str | None = None
    workers: list[str] | None = Field(None, description="workers that answered on the queue within 1 s")


class UploadAccepted(BaseModel):
    """``POST /v1/sessions``: the job that processes the upload.

    ``session`` is the stored session's name once known (a re-upload of a processed log), else null
    until the job is done (``GET /v1/jobs/{job}`` gives it then).
    """

    job: int
    session: str | None
    status: JobStatus
    duplicate: bool = Field(description="true when the same log was uploaded before: nothing new was queued")
    sha256: str = Field(description="SHA-256 of the uploaded bytes")
    frames: int | None = Field(None, description="camera frames in the log")
    map: str | None = Field(None, description="the map the job stores the session in")


class DroppedPublic(BaseModel):
    """What reading a log dropped on its way to the engine (``process --json``'s ``dropped``)."""

    odometry_messages: int = Field(description="odometry messages dropped (non-finite or beyond the bounds)")
    frame_motions: int = Field(description="frames whose motion was dropped (zero displacement over their dt)")
    reasons: dict[str, int] = Field(description="counts by reason")


class JobPublic(BaseModel):
    """``GET /v1/jobs/{job}``."""

    job: int
    status: JobStatus
    progress: float = Field(ge=0.0, le=1.0, description="fraction of the log's frames processed")
    error: str | None
    session: str | None
    map: str | None
    upload: str | None
    preset: str | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    dropped: DroppedPublic | None = Field(None, description="what reading the log dropped, when it dropped anything")


class JobsPublic(BaseModel):
    """``GET /v1/jobs``: one page of jobs, newest first."""

    jobs: list[JobPublic]
    total: int = Field(description="jobs matching the filters, on every page")
    next: int | None = Field(description="the `before` of the next page (null: this is the last)")


class MapHealthPublic(BaseModel):
    """A map's health: how well its active links agree (issue 12)."""

    residual: float = Field(
        description="RMS over the active links of residual / drift expected over one link length (≈0.5–1.2 consistent)"
    )
    worst: float = Field(default=0.0, description="the largest of those normalised residuals (over 3: inconsistent)")
    switched_off: int = Field(description="links switched off by robust relaxation (stored, not used)")
    links: int
    unmeasured: int = Field(
        default=0, description="active links whose residual is not finite (an infinity stored in a link or pose)"
    )


class MapSummaryPublic(BaseModel):
    """One map in ``GET /v1/maps``."""

    name: str
    sessions: int
    templates: int
    experiences: int
    links: int
    health: MapHealthPublic | None = None
    merges: dict[str, int] = Field(
        default_factory=dict, description="merge events of this map by status: applied, rejected, undone"
    )
    archived_at: datetime | None = Field(None, description="when the map was deleted (archived maps only)")


class MapRenamePublic(BaseModel):
    """``PATCH /v1/maps/{name}``: the map's new name."""

    name: str = Field(min_length=1, max_length=200, description="the new name (the map name rule)")


class MapChangePublic(BaseModel):
    """What a lifecycle request did to a map: deleted (archived), restored, renamed or purged."""

    map: str = Field(description="the map's name (after a rename: the new one)")
    status: Literal["archived", "live", "purged"]
    archived_at: datetime | None = None
    previous: str | None = Field(None, description="the old name (rename)")
    sessions: int | None = Field(None, description="sessions deleted with the map (purge)")
    merge_events: int | None = Field(None, description="merge events deleted with the map (purge)")


class TokenPublic(BaseModel):
    """``GET /v1/token``: the token the request sent (never its characters)."""

    id: int
    scope: Literal["read", "write"]
    label: str | None = None
    expires_at: datetime | None = None


class MapsPublic(BaseModel):
    """``GET /v1/maps``."""

    maps: list[MapSummaryPublic]


class SessionPublic(BaseModel):
    """A session of a map."""

    name: str
    log_name: str
    log_sha256: str
    source: str
    status: str
    frames: int
    frames_total: int | None
    first_stamp: float | None
    last_stamp: float | None
    started_at: datetime
    finished_at: datetime | None
    frames_per_s: float | None = Field(
        default=None, description="frames processed per second from started_at to finished_at (null: unfinished)"
    )


class MergeEventPublic(BaseModel):
    """A merge that produced (part of) a map."""

    id: int
    mode: str
    status: MergeStatus
    confirmations: int
    created_at: datetime
    undone_at: datetime | None
    sessions: dict[str, str] = Field(description="session name → role (target or source)")
    transform: list[float] = Field(description="tx, ty, tz, qx, qy, qz, qw applied to the source")
    yaw: float
    lattice_offset: list[float] = Field(description="pose-cell offset (cells) applied to the source: x, y, [z,] th")
    matches: dict[str, Any] = Field(
        description="matched templates and experiences: anchor pair, identified pairs (target/source ids and uids)"
    )


class MapPublic(BaseModel):
    """``GET /v1/maps/{name}``: one map with its sessions and merge events."""

    name: str
    version: int = Field(description="write counter: increases with every change of the map")
    templates: int
    experiences: int
    links: int
    health: MapHealthPublic | None = None
    created_at: datetime
    updated_at: datetime
    params: dict[str, Any] = Field(description="the map's effective engine parameters")
    sessions: list[SessionPublic]
    merge_events: list[MergeEventPublic]


class ExperiencePublic(BaseModel):
    """An experience (pose in the map frame, metres and radians)."""

    id: int
    x: float
    y: float
    z: float
    yaw: float
    template: int
    session: str
    stamp: float


class ExperiencesPublic(BaseModel):
    """``GET /v1/maps/{name}/experiences``: one page."""

    experiences: list[ExperiencePublic]
    total: int
    offset: int
    limit: int


class PosePublic(BaseModel):
    """A pose on a path."""

    x: float
    y: float
    z: float
    yaw: float


class PathPublic(BaseModel):
    """``GET /v1/maps/{name}/path``."""

    nodes: list[int]
    poses: list[PosePublic]
    cost: float
    weight: Literal["time", "distance"]

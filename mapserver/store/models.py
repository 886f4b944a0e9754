"""SQLAlchemy 2 ORM models: the whole schema of the map store (see docs/architecture.md, "Store").

Only the Alembic migrations under ``migrations/`` build this schema (tests included); a test checks
that autogenerate finds no difference between these models and the migrations.

Identity of map content
    A map's templates and experiences have *map-local* ids (``local_id``: the row index in the engine
    snapshot) that a merge renumbers, and a *stable* identity that never changes: the session that
    created them (``session_id``) and their index among that session's templates/experiences
    (``origin_index``). Evidence and provenance hang on the stable identity.

Ownership
    A template or experience belongs to at most one map at a time. Template rows are immutable and
    never deleted by a save: when no map holds one any more (its map was dropped or merged away) it
    stays *detached* (``map_id`` NULL) because archived map states (unmerge) refer to it.
    Experiences, links and LVC→pose-cell links are rewritten wholesale on every save of their map.

Floating point columns are IEEE doubles (``DOUBLE PRECISION`` / SQLite ``REAL``); the state loader
restores the sign of zeros that SQLite drops (see :mod:`mapserver.store.state`).
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, ClassVar

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    CheckConstraint,
    DateTime,
    Double,
    ForeignKey,
    ForeignKeyConstraint,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    SmallInteger,
    String,
    Table,
    Text,
    UniqueConstraint,
)
from sqlalchemy import true as sa_true
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column
from sqlalchemy.types import TypeDecorator

from mapserver.formats import LINK_KIND_NAMES
from mapserver.statuses import MergeStatus

NAMING_CONVENTION: dict[str, str] = {
    "ix": "ix_%(table_name)s_%(column_0_N_name)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_N_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

Id = BigInteger().with_variant(Integer(), "sqlite")
"""Surrogate primary keys: BIGINT, but INTEGER on SQLite so that the column aliases the rowid."""

SESSION_STATUSES: tuple[str, ...] = ("partial", "complete")
JOB_STATUSES: tuple[str, ...] = ("queued", "running", "done", "failed")
TOKEN_SCOPES: tuple[str, ...] = ("read", "write")
MERGE_STATUSES: tuple[str, ...] = tuple(MergeStatus)


def utcnow() -> datetime:
    """Return the current time, timezone-aware UTC."""
    return datetime.now(UTC)


class UtcDateTime(TypeDecorator[datetime]):
    """A timestamp stored in UTC and always read back timezone-aware (SQLite returns naive values)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        """Convert aware values to UTC; naive values are taken as UTC."""
        del dialect
        if value is None:
            return None
        return value.astimezone(UTC) if value.tzinfo is not None else value.replace(tzinfo=UTC)

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        """Return the value as an aware UTC datetime."""
        del dialect
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


def _in(column: str, values: tuple[str, ...]) -> str:
    return f"{column} IN ({', '.join(repr(v) for v in values)})"


class Base(DeclarativeBase):
    """Declarative base with the constraint naming convention the migrations use."""

    __table__: ClassVar[Table]  # every model here is mapped to a Table (DeclarativeBase types it FromClause)
    metadata = MetaData(naming_convention=NAMING_CONVENTION)
    type_annotation_map: ClassVar[dict[Any, Any]] = {
        float: Double(),
        int: BigInteger(),
        str: String(200),
        datetime: UtcDateTime(),
    }


class Map(Base):
    """A map: one set of templates, one pose-cell lattice, one experience graph; one or more sessions.

    ``version`` is incremented by every write of the map's state; writers check it (optimistic
    concurrency) so that two processes never interleave their states. ``archived_at`` marks a deleted map
    (:mod:`mapserver.store.lifecycle`): hidden from lookups and listings, everything it holds kept.
    """

    __tablename__ = "maps"
    __table_args__ = ({"sqlite_autoincrement": True},)

    id: Mapped[int] = mapped_column(Id, primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    version: Mapped[int] = mapped_column(BigInteger, default=0)
    params: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    #: set when the map is deleted (archived, restorable; migration 0009); NULL for a live map
    archived_at: Mapped[datetime | None] = mapped_column(UtcDateTime, nullable=True)


class Session(Base):
    """One processed mission log (or one imported map): provenance, progress and map membership.

    ``status`` is ``partial`` while frames remain (``process --stop-after``) and ``complete`` after
    the last frame. A log is identified by its SHA-256 and topic mapping (``topics_key``); processing
    it again continues the partial session or answers with the complete one.
    """

    __tablename__ = "sessions"
    __table_args__ = (
        UniqueConstraint("log_sha256", "topics_key"),
        CheckConstraint(_in("status", SESSION_STATUSES), name="status"),
        {"sqlite_autoincrement": True},
    )

    id: Mapped[int] = mapped_column(Id, primary_key=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    map_id: Mapped[int | None] = mapped_column(ForeignKey("maps.id", ondelete="SET NULL"), index=True)
    source: Mapped[str] = mapped_column(String(40))
    log_name: Mapped[str] = mapped_column(String(500))
    log_sha256: Mapped[str] = mapped_column(String(64), index=True)
    topics: Mapped[dict[str, Any]] = mapped_column(JSON)
    topics_key: Mapped[str] = mapped_column(String(64))
    params: Mapped[dict[str, Any]] = mapped_column(JSON)
    code_version: Mapped[str] = mapped_column(String(64))
    status: Mapped[str] = mapped_column(String(16))
    frames_processed: Mapped[int] = mapped_column(BigInteger)
    frames_total: Mapped[int | None] = mapped_column(BigInteger)
    first_stamp: Mapped[float | None] = mapped_column(Double)
    last_stamp: Mapped[float | None] = mapped_column(Double)
    reckoning: Mapped[bytes | None] = mapped_column(LargeBinary)
    reckoning_pose: Mapped[list[float] | None] = mapped_column(JSON)
    #: per frame ``[stamp, template session, template origin index, created]`` (float64 LE, N × 4): the
    #: activation timeline (mapserver.store.sessions.get_activations); NULL before migration 0005
    activations: Mapped[bytes | None] = mapped_column(LargeBinary)
    #: the log's ground truth ``[stamp, x, y, z, qx, qy, qz, qw]`` (float64 LE, N × 8), decimated
    #: (mapserver.store.ground_truth); NULL when the session has none (and before migration 0009)
    ground_truth: Mapped[bytes | None] = mapped_column(LargeBinary)
    started_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    finished_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    updated_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)


class Template(Base):
    """A local view cell template (immutable once stored): float32 pixels, mean and shape."""

    __tablename__ = "templates"
    __table_args__ = (UniqueConstraint("map_id", "local_id"),)

    session_id: Mapped[int] = mapped_column(ForeignKey("sessions.id", ondelete="CASCADE"), primary_key=True)
    origin_index: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    map_id: Mapped[int | None] = mapped_column(ForeignKey("maps.id", ondelete="SET NULL"))
    local_id: Mapped[int | None] = mapped_column(BigInteger)
    height: Mapped[int] = mapped_column(Integer)
    width: Mapped[int] = mapped_column(Integer)
    mean: Mapped[float] = mapped_column(Double)
    data: Mapped[bytes] = mapped_column(LargeBinary)


class PoseCellLink(Base):
    """An LVC→pose-cell link β: template, lattice coordinates, strength and decay (row order kept)."""

    __tablename__ = "pose_cell_links"
    __table_args__ = (
        ForeignKeyConstraint(["map_id", "template"], ["templates.map_id", "templates.local_id"]),
        Index("ix_pose_cell_links_map_id_template", "map_id", "template"),
    )

    map_id: Mapped[int] = mapped_column(ForeignKey("maps.id", ondelete="CASCADE"), primary_key=True)
    seq: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    template: Mapped[int] = mapped_column(BigInteger)
    pc_x: Mapped[float] = mapped_column(Double)
    pc_y: Mapped[float] = mapped_column(Double)
    pc_z: Mapped[float | None] = mapped_column(Double)
    pc_th: Mapped[float] = mapped_column(Double)
    strength: Mapped[float] = mapped_column(Double)
    decay: Mapped[float] = mapped_column(Double)


class Experience(Base):
    """An experience: SE(3) pose (+ yaw), lattice coordinates, template, stamp and stable identity."""

    __tablename__ = "experiences"
    __table_args__ = (
        UniqueConstraint("session_id", "origin_index"),
        ForeignKeyConstraint(["map_id", "template"], ["templates.map_id", "templates.local_id"]),
    )

    map_id: Mapped[int] = mapped_column(ForeignKey("maps.id", ondelete="CASCADE"), primary_key=True)
    local_id: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    session_id: Mapped[int] = mapped_column(ForeignKey("sessions.id", ondelete="CASCADE"))
    origin_index: Mapped[int] = mapped_column(BigInteger)
    x: Mapped[float] = mapped_column(Double)
    y: Mapped[float] = mapped_column(Double)
    z: Mapped[float] = mapped_column(Double)
    qx: Mapped[float] = mapped_column(Double)
    qy: Mapped[float] = mapped_column(Double)
    qz: Mapped[float] = mapped_column(Double)
    qw: Mapped[float] = mapped_column(Double)
    yaw: Mapped[float] = mapped_column(Double)
    pc_x: Mapped[float] = mapped_column(Double)
    pc_y: Mapped[float] = mapped_column(Double)
    pc_z: Mapped[float | None] = mapped_column(Double)
    pc_th: Mapped[float] = mapped_column(Double)
    template: Mapped[int] = mapped_column(BigInteger)
    stamp: Mapped[float] = mapped_column(Double)


class Link(Base):
    """A directed experience link: pose of ``to_id`` in the frame of ``from_id``, Δt, distance, kind."""

    __tablename__ = "links"
    __table_args__ = (
        ForeignKeyConstraint(["map_id", "from_id"], ["experiences.map_id", "experiences.local_id"]),
        ForeignKeyConstraint(["map_id", "to_id"], ["experiences.map_id", "experiences.local_id"]),
        CheckConstraint(_in("kind", LINK_KIND_NAMES), name="kind"),
        Index("ix_links_map_id_from_id", "map_id", "from_id"),
        Index("ix_links_map_id_to_id", "map_id", "to_id"),
    )

    map_id: Mapped[int] = mapped_column(ForeignKey("maps.id", ondelete="CASCADE"), primary_key=True)
    seq: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    from_id: Mapped[int] = mapped_column(BigInteger)
    to_id: Mapped[int] = mapped_column(BigInteger)
    dx: Mapped[float] = mapped_column(Double)
    dy: Mapped[float] = mapped_column(Double)
    dz: Mapped[float] = mapped_column(Double)
    dyaw: Mapped[float] = mapped_column(Double)
    dt: Mapped[float] = mapped_column(Double)
    distance: Mapped[float] = mapped_column(Double)
    kind: Mapped[str] = mapped_column(String(16))
    #: False when robust relaxation switched the link off (core.robust); migration 0004
    active: Mapped[bool] = mapped_column(Boolean, server_default=sa_true(), default=True, nullable=False)


class MapState(Base):
    """The engine state of a map that the row tables do not hold (resume exactly where it stopped).

    ``pc_activity`` is the pose-cell activity (zlib-compressed float64); ``arrays`` is a compressed
    npz of every other snapshot key not stored in a row table (current template and experience,
    odometry accumulators, VO profiles, gate state, any key a newer engine adds) plus the exactness
    patches; ``manifest`` lists every snapshot key with dtype, shape and where it is stored. The
    scalar columns are copies for queries.
    """

    __tablename__ = "map_states"

    map_id: Mapped[int] = mapped_column(ForeignKey("maps.id", ondelete="CASCADE"), primary_key=True)
    lattice_rank: Mapped[int] = mapped_column(SmallInteger)
    frames: Mapped[int] = mapped_column(BigInteger)
    last_stamp: Mapped[float | None] = mapped_column(Double)
    current_template: Mapped[int] = mapped_column(BigInteger)
    current_experience: Mapped[int] = mapped_column(BigInteger)
    n_templates: Mapped[int] = mapped_column(BigInteger)
    n_experiences: Mapped[int] = mapped_column(BigInteger)
    n_links: Mapped[int] = mapped_column(BigInteger)
    n_pose_cell_links: Mapped[int] = mapped_column(BigInteger)
    pc_activity: Mapped[bytes] = mapped_column(LargeBinary)
    arrays: Mapped[bytes] = mapped_column(LargeBinary)
    manifest: Mapped[dict[str, Any]] = mapped_column(JSON)
    #: {"residual", "switched_off", "links"} when the state was written (mapserver.store.health); migration 0004
    health: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    updated_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)


class Evidence(Base):
    """The camera frame closest to an experience's stamp, as a small JPEG (keyed by stable identity)."""

    __tablename__ = "evidence"

    session_id: Mapped[int] = mapped_column(ForeignKey("sessions.id", ondelete="CASCADE"), primary_key=True)
    origin_index: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    frame_stamp: Mapped[float] = mapped_column(Double)
    offset_s: Mapped[float] = mapped_column(Double)
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    media_type: Mapped[str] = mapped_column(String(40))
    data: Mapped[bytes] = mapped_column(LargeBinary)


class MergeEvent(Base):
    """One merge: maps and sessions joined, matches, lattice offset, SE(3) transform, confirmations.

    ``map_id`` is the map the merge produced. The pre-merge states of every map involved are
    :class:`MapArchive` rows pointing here, so the merge can be undone (``status`` → ``undone``).
    ``tx``…``qw`` is the SE(3) transform applied to the joined map's poses (``yaw`` for convenience).
    """

    __tablename__ = "merge_events"
    __table_args__ = (
        CheckConstraint(_in("status", MERGE_STATUSES), name="status"),
        Index("ix_merge_events_map_id_created_at", "map_id", "created_at"),
        {"sqlite_autoincrement": True},
    )

    id: Mapped[int] = mapped_column(Id, primary_key=True)
    map_id: Mapped[int | None] = mapped_column(ForeignKey("maps.id", ondelete="SET NULL"))
    map_name: Mapped[str] = mapped_column(String(200))
    mode: Mapped[str] = mapped_column(String(16))
    status: Mapped[str] = mapped_column(String(16))
    confirmations: Mapped[int] = mapped_column(Integer)
    lattice_offset: Mapped[list[float]] = mapped_column(JSON)
    tx: Mapped[float] = mapped_column(Double)
    ty: Mapped[float] = mapped_column(Double)
    tz: Mapped[float] = mapped_column(Double)
    qx: Mapped[float] = mapped_column(Double)
    qy: Mapped[float] = mapped_column(Double)
    qz: Mapped[float] = mapped_column(Double)
    qw: Mapped[float] = mapped_column(Double)
    yaw: Mapped[float] = mapped_column(Double)
    matches: Mapped[dict[str, Any]] = mapped_column(JSON)
    details: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    undone_at: Mapped[datetime | None] = mapped_column(UtcDateTime)


class MergeEventSession(Base):
    """A session involved in a merge event and its side (``target`` or ``source``)."""

    __tablename__ = "merge_event_sessions"

    event_id: Mapped[int] = mapped_column(ForeignKey("merge_events.id", ondelete="CASCADE"), primary_key=True)
    session_id: Mapped[int] = mapped_column(ForeignKey("sessions.id", ondelete="CASCADE"), primary_key=True)
    role: Mapped[str] = mapped_column(String(16))


class MapArchive(Base):
    """A frozen map state (e.g. a map's state before a merge), restorable exactly.

    ``state`` is a compressed npz of the snapshot in which templates already stored as
    :class:`Template` rows are referenced by stable identity instead of copied.
    """

    __tablename__ = "map_archives"
    __table_args__ = ({"sqlite_autoincrement": True},)

    id: Mapped[int] = mapped_column(Id, primary_key=True)
    event_id: Mapped[int | None] = mapped_column(ForeignKey("merge_events.id", ondelete="CASCADE"), index=True)
    role: Mapped[str | None] = mapped_column(String(16))
    map_id: Mapped[int | None] = mapped_column(ForeignKey("maps.id", ondelete="SET NULL"))
    map_name: Mapped[str] = mapped_column(String(200))
    map_version: Mapped[int | None] = mapped_column(BigInteger)
    params: Mapped[dict[str, Any]] = mapped_column(JSON)
    session_ids: Mapped[list[int]] = mapped_column(JSON)
    n_templates: Mapped[int] = mapped_column(BigInteger)
    n_experiences: Mapped[int] = mapped_column(BigInteger)
    n_links: Mapped[int] = mapped_column(BigInteger)
    state: Mapped[bytes] = mapped_column(LargeBinary)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)


class Blob(Base):
    """A large array many map states share, stored once per database under its SHA-256 (``mapserver.store.blobs``).

    ``data`` is the array's ``.npy`` bytes (dtype, shape and every bit); map states and archives hold its digest.
    Today: the ``sdr-htm`` front-end's LSBH projection, the same for every map made with one seed and size.
    """

    __tablename__ = "blobs"

    digest: Mapped[str] = mapped_column(String(64), primary_key=True)
    nbytes: Mapped[int] = mapped_column(BigInteger)
    data: Mapped[bytes] = mapped_column(LargeBinary)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)


class ApiToken(Base):
    """A REST API bearer token; only its SHA-256 is stored."""

    __tablename__ = "api_tokens"
    __table_args__ = (
        CheckConstraint(_in("scope", TOKEN_SCOPES), name="scope"),
        {"sqlite_autoincrement": True},
    )

    id: Mapped[int] = mapped_column(Id, primary_key=True)
    token_sha256: Mapped[str] = mapped_column(String(64), unique=True)
    prefix: Mapped[str] = mapped_column(String(16))
    scope: Mapped[str] = mapped_column(String(8))
    label: Mapped[str | None] = mapped_column(String(200))
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    last_used_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    revoked_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    #: NULL: never expires (migration 0008)
    expires_at: Mapped[datetime | None] = mapped_column(UtcDateTime, nullable=True)


class Job(Base):
    """A queued upload-processing job of the REST API."""

    __tablename__ = "jobs"
    __table_args__ = (
        CheckConstraint(_in("status", JOB_STATUSES), name="status"),
        CheckConstraint("progress >= 0 AND progress <= 1", name="progress"),
        Index("ix_jobs_status_created_at", "status", "created_at"),
        Index("ix_jobs_map_name_status", "map_name", "status"),
        {"sqlite_autoincrement": True},
    )

    id: Mapped[int] = mapped_column(Id, primary_key=True)
    status: Mapped[str] = mapped_column(String(16))
    progress: Mapped[float] = mapped_column(Double, default=0.0)
    error: Mapped[str | None] = mapped_column(Text)
    session_id: Mapped[int | None] = mapped_column(ForeignKey("sessions.id", ondelete="SET NULL"))
    map_id: Mapped[int | None] = mapped_column(ForeignKey("maps.id", ondelete="SET NULL"))
    map_name: Mapped[str | None] = mapped_column(String(200))
    upload_path: Mapped[str] = mapped_column(String(1000))
    upload_name: Mapped[str | None] = mapped_column(String(500))
    upload_sha256: Mapped[str | None] = mapped_column(String(64), index=True)
    preset: Mapped[str | None] = mapped_column(String(64))
    topics: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    options: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    finished_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    updated_at: Mapped[datetime] = mapped_column(UtcDateTime, default=utcnow)
    lease_owner: Mapped[str | None] = mapped_column(String(200))
    lease_expires_at: Mapped[datetime | None] = mapped_column(UtcDateTime)
    lease_token: Mapped[int] = mapped_column(BigInteger, default=0, server_default="0")

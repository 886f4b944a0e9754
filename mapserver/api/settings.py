"""Typed settings of the REST API server (``mapserver serve``), read from arguments or the environment."""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path

from core.config import ConfigError
from mapserver.api.archives import ArchiveLimits
from mapserver.ingest.decode import DEFAULT_MAX_IMAGE_PIXELS
from mapserver.store import DEFAULT_DB_URL

ENV_PREFIX = "MAPSERVER_"
GIB = 1 << 30
LIMITS = ("max_upload_bytes", "max_unpacked_bytes", "max_unpacked_ratio", "max_archive_entries", "max_image_pixels",
          "max_trailing_bytes", "max_exports", "read_timeout_s")  # fmt: skip


@dataclass(frozen=True, slots=True)
class Settings:
    """Everything the API server needs to know; immutable, validated on construction.

    Attributes:
        db_url: SQLAlchemy URL of the map store (an empty database gets the schema on start).
        upload_dir: where uploaded logs are kept (None: ``uploads/`` beside a SQLite file, else ``./var/uploads``).
        max_upload_bytes: largest accepted upload (the request body's file part); larger → 413.
        max_unpacked_bytes: most bytes one archive upload may unpack to (counted as they are decompressed).
        max_unpacked_ratio: an archive may unpack to at most this multiple of its own size (the smaller of
            the two byte limits applies).
        max_archive_entries: most entries (files and directories) one archive upload may hold.
        max_image_pixels: most pixels (width × height) of one camera frame, read from the image's header
            before it is decoded, at upload and in every job.
        workers: worker threads of the embedded job engine (different maps run in parallel).
        allow_anonymous_reads: GET endpoints need no token.
        host: interface ``serve`` binds to.
        port: TCP port ``serve`` listens on.
        progress_interval_s: a job writes its progress to the database at most this often.
        max_job_attempts: a job interrupted by a server stop this many times is failed instead of rerun.
        graph_cache_maps: how many maps' path graphs are kept in memory.
        jobs: job engine, ``embedded`` (threads in this process) or ``celery`` (``mapserver worker``
            processes; PostgreSQL only).
        broker_url: Celery broker URL (``redis://…`` or ``amqp://…``; default the local Redis).
        job_queue: the Celery queue the workers consume.
        lease_s: a running job's lease, for the Celery workers (dispatch is repeated after twice this) and the
            embedded engine (renewed every third of it; another server takes over a job whose lease expired).
        keep_uploads_days: a job's upload folder is kept until the job is processed (done or failed), then
            this many days (``inf``: forever; checked at start and every hour).
        max_exports: most map exports (``GET /v1/maps/{name}/export``) running at once; more get 503 with
            ``Retry-After``.
        read_timeout_s: an upload that sends no byte for this long is answered 408 and its connection closed.
        max_trailing_bytes: most bytes an upload's body may carry after its multipart closing boundary (an
            epilogue); more is refused (400) without reading the rest.
    """

    db_url: str = DEFAULT_DB_URL
    upload_dir: Path | None = None
    max_upload_bytes: int = 4 * GIB
    max_unpacked_bytes: int = 8 * GIB
    max_unpacked_ratio: float = 200.0
    max_archive_entries: int = 1000
    max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS
    workers: int = 2
    allow_anonymous_reads: bool = False
    host: str = "127.0.0.1"
    port: int = 8000
    progress_interval_s: float = 0.5
    max_job_attempts: int = 3
    graph_cache_maps: int = 8
    jobs: str = "embedded"
    broker_url: str = "redis://127.0.0.1:6379/0"
    job_queue: str = "mapserver"
    lease_s: float = 30.0
    keep_uploads_days: float = 7.0
    max_exports: int = 4
    read_timeout_s: float = 60.0
    max_trailing_bytes: int = 1024

    def __post_init__(self) -> None:
        checks = {
            "max_upload_bytes": self.max_upload_bytes >= 1,
            "max_unpacked_bytes": self.max_unpacked_bytes >= 1,
            "max_unpacked_ratio": self.max_unpacked_ratio >= 1 and math.isfinite(self.max_unpacked_ratio),
            "max_archive_entries": self.max_archive_entries >= 1,
            "max_image_pixels": self.max_image_pixels >= 1,
            "workers": 1 <= self.workers <= 64,
            "port": 0 <= self.port <= 65535,
            "progress_interval_s": self.progress_interval_s >= 0,
            "max_job_attempts": self.max_job_attempts >= 1,
            "graph_cache_maps": self.graph_cache_maps >= 1,
            "jobs": self.jobs in ("embedded", "celery"),
            "lease_s": self.lease_s > 0,
            "keep_uploads_days": self.keep_uploads_days >= 0,
            "max_exports": 1 <= self.max_exports <= 1024,
            "read_timeout_s": 0 < self.read_timeout_s <= 86_400,
            "max_trailing_bytes": self.max_trailing_bytes >= 0,
        }
        for name, ok in checks.items():
            if not ok:
                msg = f"invalid server setting {name}={getattr(self, name)!r}"
                raise ConfigError(msg)
        if self.jobs == "celery" and not self.db_url.startswith("postgresql"):
            msg = (
                f"--jobs celery needs a PostgreSQL database (--db postgresql+psycopg://...), got {self.db_url!r}: "
                "workers on other machines cannot share a SQLite file"
            )
            raise ConfigError(msg)

    @property
    def uploads(self) -> Path:
        """Return the upload directory (see ``upload_dir``)."""
        if self.upload_dir is not None:
            return Path(self.upload_dir)
        if self.db_url.startswith("sqlite:///") and ":memory:" not in self.db_url:
            database = Path(self.db_url.removeprefix("sqlite:///").split("?", 1)[0])
            return database.parent / "uploads"
        return Path("var") / "uploads"

    @property
    def archive_limits(self) -> ArchiveLimits:
        """Return what one archive upload may unpack to."""
        return ArchiveLimits(self.max_unpacked_bytes, self.max_unpacked_ratio, self.max_archive_entries)

    def limits(self) -> dict[str, int | float]:
        """Return the limits ``GET /v1/limits`` lists, by name (each refusal names one of them)."""
        return {name: getattr(self, name) for name in LIMITS}

    def with_overrides(self, **values: object) -> Settings:
        """Return a copy with the non-None ``values`` replaced."""
        chosen = {k: v for k, v in values.items() if v is not None}
        return replace(self, **chosen)  # type: ignore[arg-type]

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> Settings:
        """Return the defaults overridden by ``MAPSERVER_*`` environment variables.

        Variables: ``MAPSERVER_DB``, ``MAPSERVER_UPLOAD_DIR``, ``MAPSERVER_MAX_UPLOAD_BYTES``,
        ``MAPSERVER_MAX_UNPACKED_BYTES``, ``MAPSERVER_MAX_UNPACKED_RATIO``, ``MAPSERVER_MAX_ARCHIVE_ENTRIES``,
        ``MAPSERVER_MAX_IMAGE_PIXELS``, ``MAPSERVER_MAX_TRAILING_BYTES``, ``MAPSERVER_MAX_EXPORTS``,
        ``MAPSERVER_READ_TIMEOUT_S``, ``MAPSERVER_WORKERS``, ``MAPSERVER_ALLOW_ANONYMOUS_READS``
        (1/true/yes), ``MAPSERVER_HOST``, ``MAPSERVER_PORT``, ``MAPSERVER_JOBS``, ``MAPSERVER_BROKER``.

        Raises:
            ConfigError: a variable does not parse.
        """
        env = os.environ if environ is None else environ
        values: dict[str, object] = {}
        text = {"DB": "db_url", "UPLOAD_DIR": "upload_dir", "HOST": "host", "JOBS": "jobs", "BROKER": "broker_url"}
        numbers = {"MAX_UPLOAD_BYTES": "max_upload_bytes", "MAX_UNPACKED_BYTES": "max_unpacked_bytes",
                   "MAX_ARCHIVE_ENTRIES": "max_archive_entries", "MAX_IMAGE_PIXELS": "max_image_pixels",
                   "MAX_TRAILING_BYTES": "max_trailing_bytes", "MAX_EXPORTS": "max_exports",
                   "WORKERS": "workers", "PORT": "port"}  # fmt: skip
        for key, field in text.items():
            if (value := env.get(ENV_PREFIX + key)) is not None:
                values[field] = Path(value) if field == "upload_dir" else value
        for key, field in numbers.items():
            if (value := env.get(ENV_PREFIX + key)) is not None:
                try:
                    values[field] = int(value)
                except ValueError as err:
                    msg = f"{ENV_PREFIX}{key} must be an integer, got {value!r}"
                    raise ConfigError(msg) from err
        for key, field in (("MAX_UNPACKED_RATIO", "max_unpacked_ratio"), ("READ_TIMEOUT_S", "read_timeout_s")):
            if (value := env.get(ENV_PREFIX + key)) is not None:
                try:
                    values[field] = float(value)
                except ValueError as err:
                    msg = f"{ENV_PREFIX}{key} must be a number, got {value!r}"
                    raise ConfigError(msg) from err
        if (flag := env.get(ENV_PREFIX + "ALLOW_ANONYMOUS_READS")) is not None:
            values["allow_anonymous_reads"] = flag.strip().lower() in ("1", "true", "yes", "on")
        return cls().with_overrides(**values)

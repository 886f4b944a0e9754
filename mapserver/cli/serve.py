"""``mapserver serve [--db URL] [--host H] [--port P] [--jobs embedded|celery --broker URL]``: run the REST API.

The ``--max-*`` flags set the limits uploads are refused by (``GET /v1/limits`` lists them).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mapserver.api import Settings
from mapserver.api.lifecycle import claim_server, serve_forever
from mapserver.cli._output import info
from mapserver.store import open_database


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``serve`` command."""
    defaults = Settings()
    parser = subparsers.add_parser("serve", help="run the REST API server")
    parser.add_argument("--db", help=f"SQLAlchemy URL (default: $MAPSERVER_DB or {defaults.db_url})")
    parser.add_argument("--host", help=f"interface to bind (default: {defaults.host})")
    parser.add_argument("--port", type=int, help=f"TCP port (default: {defaults.port})")
    parser.add_argument("--allow-anonymous-reads", action="store_true", default=None,
                        help="let GET requests through without a token")  # fmt: skip
    parser.add_argument("--workers", type=int, help=f"job worker threads (default: {defaults.workers})")
    parser.add_argument("--upload-dir", type=Path, help="where uploads are kept (default: uploads/ beside the DB)")
    parser.add_argument("--max-upload-bytes", type=int,
                        help=f"largest accepted upload (default: {defaults.max_upload_bytes})")  # fmt: skip
    parser.add_argument("--max-unpacked-bytes", type=int,
                        help=f"most bytes one archive upload may unpack to (default: {defaults.max_unpacked_bytes})")
    parser.add_argument("--max-unpacked-ratio", type=float,
                        help="an archive upload may unpack to at most this multiple of its own size "
                             f"(default: {defaults.max_unpacked_ratio:g})")  # fmt: skip
    parser.add_argument("--max-archive-entries", type=int,
                        help=f"most entries in one archive upload (default: {defaults.max_archive_entries})")
    parser.add_argument("--max-image-pixels", type=int,
                        help="most pixels of one camera frame, read from its header before decoding "
                             f"(default: {defaults.max_image_pixels})")  # fmt: skip
    parser.add_argument("--jobs", choices=("embedded", "celery"),
                        help="job engine: threads in this process, or `mapserver worker` processes (PostgreSQL only)")
    parser.add_argument("--broker", help=f"Celery broker URL for --jobs celery (default: {defaults.broker_url})")
    parser.add_argument("--queue", help=f"Celery queue of the workers (default: {defaults.job_queue})")
    parser.add_argument("--lease-seconds", type=float, help=f"workers' job lease (default: {defaults.lease_s})")
    parser.add_argument("--max-exports", type=int,
                        help=f"most map exports at once; more are answered 503 (default: {defaults.max_exports})")
    parser.add_argument("--max-trailing-bytes", type=int,
                        help="most bytes an upload may send after its multipart closing boundary "
                             f"(default: {defaults.max_trailing_bytes})")  # fmt: skip
    parser.add_argument("--read-timeout", type=float, dest="read_timeout",
                        help="seconds an upload may send nothing before it is answered 408 "
                             f"(default: {defaults.read_timeout_s:g})")  # fmt: skip
    parser.add_argument("--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"),
                        help="server log level (default: info)")  # fmt: skip
    parser.add_argument("--keep-uploads-days", type=float,
                        help="keep a processed job's upload this many days, then remove it; inf keeps it "
                             f"(default: {defaults.keep_uploads_days:g})")  # fmt: skip
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Check the database (creating an empty one's schema), then serve until interrupted.

    A second server with the embedded job engine on the same SQLite database, or on a taken port, is
    refused with one line (exit 1) before it touches any job.
    """
    settings = Settings.from_env().with_overrides(
        db_url=args.db, host=args.host, port=args.port, allow_anonymous_reads=args.allow_anonymous_reads,
        workers=args.workers, upload_dir=args.upload_dir, max_upload_bytes=args.max_upload_bytes,
        max_unpacked_bytes=args.max_unpacked_bytes, max_unpacked_ratio=args.max_unpacked_ratio,
        max_archive_entries=args.max_archive_entries, max_image_pixels=args.max_image_pixels,
        jobs=args.jobs, broker_url=args.broker, job_queue=args.queue, lease_s=args.lease_seconds,
        keep_uploads_days=args.keep_uploads_days, max_exports=args.max_exports, read_timeout_s=args.read_timeout,
        max_trailing_bytes=args.max_trailing_bytes,
    )  # fmt: skip
    with open_database(settings.db_url) as db:  # fail here, with one ERROR line, on a bad or old database
        url = db.display_url()
    claim = claim_server(settings)  # the database's server lock, then the port: refused here, in one line
    reads = "anonymous reads allowed" if settings.allow_anonymous_reads else "reads need a token"
    jobs = f"jobs on Celery workers, queue {settings.job_queue!r}" if settings.jobs == "celery" else "embedded jobs"
    info(f"serving {url} on http://{settings.host}:{settings.port} ({reads}; {jobs}; docs at /docs)")
    info("limits: " + ", ".join(f"{name} {value:g}" for name, value in settings.limits().items()))
    serve_forever(settings, claim, log_level=args.log_level)  # the app and its jobs start on the claimed port
    return 0

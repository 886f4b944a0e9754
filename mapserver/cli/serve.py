"""``mapserver serve [--db URL] [--host H] [--port P] [--jobs embedded|celery --broker URL]``: run the REST API."""

from __future__ import annotations

import argparse
from pathlib import Path

from mapserver.api import Settings, create_app
from mapserver.cli._output import info
from mapserver.store import open_database


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
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
    parser.add_argument("--jobs", choices=("embedded", "celery"),
                        help="job engine: threads in this process, or `mapserver worker` processes (PostgreSQL only)")
    parser.add_argument("--broker", help=f"Celery broker URL for --jobs celery (default: {defaults.broker_url})")
    parser.add_argument("--queue", help=f"Celery queue of the workers (default: {defaults.job_queue})")
    parser.add_argument("--lease-seconds", type=float, help=f"workers' job lease (default: {defaults.lease_s})")
    parser.add_argument("--max-exports", type=int,
                        help=f"most map exports at once; more are answered 503 (default: {defaults.max_exports})")
    parser.add_argument("--read-timeout", type=float, dest="read_timeout",
                        help="seconds an upload may send nothing before it is answered 408 "
                             f"(default: {defaults.read_timeout_s:g})")  # fmt: skip
    parser.add_argument("--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"),
                        help="server log level (default: info)")  # fmt: skip
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Check the database (creating an empty one's schema), then serve until interrupted."""
    import uvicorn

    settings = Settings.from_env().with_overrides(
        db_url=args.db, host=args.host, port=args.port, allow_anonymous_reads=args.allow_anonymous_reads,
        workers=args.workers, upload_dir=args.upload_dir, max_upload_bytes=args.max_upload_bytes,
        jobs=args.jobs, broker_url=args.broker, job_queue=args.queue, lease_s=args.lease_seconds,
        max_exports=args.max_exports, read_timeout_s=args.read_timeout,
    )  # fmt: skip
    with open_database(settings.db_url) as db:  # fail here, with one ERROR line, on a bad or old database
        url = db.display_url()
    reads = "anonymous reads allowed" if settings.allow_anonymous_reads else "reads need a token"
    jobs = f"jobs on Celery workers, queue {settings.job_queue!r}" if settings.jobs == "celery" else "embedded jobs"
    info(f"serving {url} on http://{settings.host}:{settings.port} ({reads}; {jobs}; docs at /docs)")
    uvicorn.run(
        create_app(settings), host=settings.host, port=settings.port, log_level=args.log_level,
        timeout_graceful_shutdown=30,
    )  # fmt: skip
    return 0

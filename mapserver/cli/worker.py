"""``mapserver worker --db URL --broker URL [--concurrency N]``: run a distributed job worker (Celery)."""

from __future__ import annotations

import argparse
import os
import socket
import uuid

from core.config import ConfigError
from mapserver.cli._output import info

DEFAULT_BROKER = "redis://127.0.0.1:6379/0"


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``worker`` command."""
    parser = subparsers.add_parser("worker", help="run a distributed job worker (Celery, PostgreSQL)")
    parser.add_argument("--db", default=os.environ.get("MAPSERVER_DB"),
                        help="PostgreSQL URL of the map store (default: $MAPSERVER_DB)")  # fmt: skip
    parser.add_argument("--broker", default=os.environ.get("MAPSERVER_BROKER", DEFAULT_BROKER),
                        help=f"Celery broker, redis://… or amqp://… (default: $MAPSERVER_BROKER or {DEFAULT_BROKER})")
    parser.add_argument("--concurrency", type=int, default=1, help="jobs run at once by this worker (default: 1)")
    parser.add_argument("--queue", default="mapserver", help="queue to consume (default: mapserver)")
    parser.add_argument("--name", help="worker name (default: a unique name on this host)")
    parser.add_argument("--lease-seconds", type=float, default=30.0, help="job lease (default: 30)")
    parser.add_argument("--max-attempts", type=int, default=3,
                        help="a job whose worker was lost this many times is failed (default: 3)")  # fmt: skip
    parser.add_argument("--pool", default="prefork", choices=("prefork", "threads", "solo"),
                        help="Celery pool (default: prefork, one process per job)")  # fmt: skip
    parser.add_argument("--max-image-pixels", type=int,
                        help="most pixels of one camera frame, read from its header before decoding "
                             "(default: $MAPSERVER_MAX_IMAGE_PIXELS or 33554432)")  # fmt: skip
    parser.add_argument("--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"))
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Check the database, then consume jobs until stopped (SIGTERM: finish the running jobs first)."""
    from mapserver.api.celery_worker import WorkerConfig, configure, serve_worker
    from mapserver.ingest.decode import PIXELS_ENV, set_max_image_pixels
    from mapserver.store import open_database

    if not args.db or not str(args.db).startswith("postgresql"):
        msg = f"mapserver worker needs a PostgreSQL database (--db postgresql+psycopg://...), got {args.db!r}"
        raise ConfigError(msg)
    if args.concurrency < 1 or args.lease_seconds <= 0 or args.max_attempts < 1:
        msg = "--concurrency and --max-attempts must be at least 1 and --lease-seconds positive"
        raise ConfigError(msg)
    if args.max_image_pixels is not None:  # the environment carries it into the pool's processes too
        set_max_image_pixels(args.max_image_pixels)
        os.environ[PIXELS_ENV] = str(args.max_image_pixels)
    with open_database(args.db) as db:  # one ERROR line on a bad or old database
        url = db.display_url()
    name = args.name or f"mapserver-{uuid.uuid4().hex[:6]}@{socket.gethostname()}"
    configure(WorkerConfig(db_url=args.db, name=name, lease_s=args.lease_seconds, max_attempts=args.max_attempts))
    info(f"worker {name}: jobs of {url} from queue {args.queue!r} on {args.broker} ({args.concurrency} at once)")
    return serve_worker(
        broker_url=args.broker, queue=args.queue, name=name, concurrency=args.concurrency, pool=args.pool,
        log_level=args.log_level,
    )  # fmt: skip

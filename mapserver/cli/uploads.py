"""``mapserver uploads prune [--db URL] [--upload-dir DIR] [--older-than DAYS] [--json]``: free the upload directory.

Removes the upload folders of jobs processed (done or failed) more than DAYS ago — the retention a server
applies by itself with ``serve --keep-uploads-days`` — and the leftovers of killed servers untouched for
an hour (staged ``.part`` files, folders no job names). Queued and running jobs' uploads are never
removed, so it is safe while servers run.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mapserver.api.housekeeping import LEFTOVER_GRACE_S, prune_uploads, remove_leftovers
from mapserver.api.settings import Settings
from mapserver.cli._output import emit_json, info
from mapserver.errors import InputError
from mapserver.store import open_database


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``uploads`` command and its ``prune`` action."""
    defaults = Settings()
    parser = subparsers.add_parser("uploads", help="manage the server's upload directory")
    actions = parser.add_subparsers(dest="uploads_action", required=True, metavar="ACTION")
    prune = actions.add_parser("prune", help="remove the uploads of jobs processed more than DAYS ago, and leftovers")
    prune.add_argument("--db", help=f"SQLAlchemy URL (default: $MAPSERVER_DB or {defaults.db_url})")
    prune.add_argument("--upload-dir", type=Path,
                       help="the server's upload directory (default: $MAPSERVER_UPLOAD_DIR, or uploads/ beside the DB)")
    prune.add_argument("--older-than", type=float, default=defaults.keep_uploads_days, metavar="DAYS",
                       help="remove uploads of jobs finished more than DAYS ago "
                            f"(default: {defaults.keep_uploads_days:g})")  # fmt: skip
    prune.add_argument("--json", action="store_true", help="print the JSON result as the last line of stdout")
    prune.set_defaults(func=run_prune)


def run_prune(args: argparse.Namespace) -> int:
    """Remove expired uploads and old leftovers; report them."""
    if not args.older_than >= 0:
        msg = f"--older-than must be 0 or more days, got {args.older_than!r}"
        raise InputError(msg)
    settings = Settings.from_env().with_overrides(db_url=args.db, upload_dir=args.upload_dir)
    root = settings.uploads
    with open_database(settings.db_url, upgrade=False) as db:
        leftovers = remove_leftovers(db, root, grace_s=LEFTOVER_GRACE_S)
        expired = prune_uploads(db, root, keep_s=args.older_than * 86400.0)
    removed = expired + leftovers
    total = sum(r.bytes for r in removed)
    info(f"{root}: removed {len(expired)} upload(s) of jobs finished more than {args.older_than:g} days ago "
         f"and {len(leftovers)} leftover(s), {total} bytes")  # fmt: skip
    if args.json:
        emit_json({
            "upload_dir": str(root), "older_than_days": args.older_than, "bytes": total,
            "removed": [r.as_dict() for r in expired], "leftovers": [r.as_dict() for r in leftovers],
        })  # fmt: skip
    return 0

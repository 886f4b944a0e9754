"""``mapserver db upgrade|current --db URL``: manage the map store's schema (Alembic migrations)."""

from __future__ import annotations

import argparse

from mapserver.cli._output import emit_json, info
from mapserver.store import DEFAULT_DB_URL, Database, create_db_engine
from mapserver.store import current_revision as _current
from mapserver.store import upgrade as _upgrade
from mapserver.store.migrate import HEAD_REVISION


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``db`` command and its ``upgrade`` and ``current`` subcommands."""
    parser = subparsers.add_parser("db", help="manage the database schema")
    actions = parser.add_subparsers(dest="db_action", required=True, metavar="ACTION")
    upgrade = actions.add_parser("upgrade", help="create or upgrade the schema to the latest revision")
    upgrade.add_argument("--revision", default="head", help="target revision (default: head)")
    current = actions.add_parser("current", help="print the schema revision")
    for sub in (upgrade, current):
        sub.add_argument("--db", default=DEFAULT_DB_URL, help=f"SQLAlchemy URL (default: {DEFAULT_DB_URL})")
        sub.add_argument("--json", action="store_true", help="print the JSON result as the last line of stdout")
    upgrade.set_defaults(func=run_upgrade)
    current.set_defaults(func=run_current)


def run_upgrade(args: argparse.Namespace) -> int:
    """Apply the migrations up to ``--revision``."""
    with Database(create_db_engine(args.db)) as db:
        before = _current(db)
        after = _upgrade(db, args.revision)
        url = db.display_url()
    info(f"{url}: schema {before or 'empty'} → {after}")
    if args.json:
        emit_json({"db": url, "from": before, "revision": after, "head": HEAD_REVISION})
    return 0


def run_current(args: argparse.Namespace) -> int:
    """Print the schema revision (``None`` for an empty database)."""
    with Database(create_db_engine(args.db)) as db:
        revision = _current(db)
        url = db.display_url()
    info(f"{url}: schema {revision or 'empty'} (this code: {HEAD_REVISION})")
    if args.json:
        emit_json({"db": url, "revision": revision, "head": HEAD_REVISION})
    return 0

"""``mapserver maps --db URL``: list the stored maps."""

from __future__ import annotations

import argparse
import sys

from mapserver.cli._output import emit_json
from mapserver.store import DEFAULT_DB_URL, list_maps, open_database


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``maps`` command."""
    parser = subparsers.add_parser("maps", help="list the stored maps")
    parser.add_argument("--db", default=DEFAULT_DB_URL, help=f"SQLAlchemy URL (default: {DEFAULT_DB_URL})")
    parser.add_argument("--json", action="store_true", help="print the JSON result as the last line of stdout")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Print one line per map (or the contract's JSON)."""
    with open_database(args.db) as db, db.read() as conn:
        maps = list_maps(conn=conn)
    if args.json:
        emit_json({"maps": [m.as_dict() for m in maps]})
        return 0
    if not maps:
        sys.stdout.write("no maps\n")
        return 0
    width = max(4, *(len(m.name) for m in maps))
    sys.stdout.write(
        f"{'name':<{width}}  sessions  templates  experiences    links  residual  off  merges (rejected, unverified)\n"
    )
    for m in maps:
        health = f"{m.health['residual']:>8.2f}  {m.health['switched_off']:>3}" if m.health else f"{'-':>8}  {'-':>3}"
        merges = m.as_dict()["merges"]
        counts = f"{merges['applied']:>6} ({merges['rejected']}, {merges['unverified']})"
        sys.stdout.write(
            f"{m.name:<{width}}  {m.sessions:>8}  {m.templates:>9}  {m.experiences:>11}  {m.links:>7}  {health}  "
            f"{counts}\n"
        )
    return 0

"""``mapserver maps [--archived]``: list the stored maps; ``maps delete|restore|rename``: a map's lifecycle.

``maps delete NAME`` archives the map (restorable with ``maps restore NAME``); ``maps delete NAME --purge``
deletes an archived map for good; ``maps rename NAME NEW`` renames a live map
(:mod:`mapserver.store.lifecycle`).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from mapserver.cli._output import emit_json, info
from mapserver.store import DEFAULT_DB_URL, MapSummary, list_maps, open_database
from mapserver.store.lifecycle import archive_map, purge_map, rename_map, restore_map


def _common(parser: argparse.ArgumentParser, *, default: Any) -> None:
    parser.add_argument("--db", default=default, help=f"SQLAlchemy URL (default: {DEFAULT_DB_URL})")
    parser.add_argument("--json", action="store_true", default=default if default is argparse.SUPPRESS else False,
                        help="print the JSON result as the last line of stdout")  # fmt: skip


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``maps`` command and its ``delete``, ``restore`` and ``rename`` subcommands."""
    parser = subparsers.add_parser("maps", help="list the stored maps; delete, restore or rename one")
    _common(parser, default=DEFAULT_DB_URL)
    parser.add_argument("--archived", action="store_true", help="list the archived (deleted, restorable) maps")
    parser.set_defaults(func=run)
    actions = parser.add_subparsers(dest="maps_action", metavar="ACTION")
    delete = actions.add_parser("delete", help="delete a map: it is archived and can be restored")
    delete.add_argument("name", help="the map")
    delete.add_argument("--purge", action="store_true",
                        help="delete an archived map for good, with its sessions and merge events")  # fmt: skip
    restore = actions.add_parser("restore", help="bring a deleted (archived) map back as it was")
    restore.add_argument("name", help="the archived map")
    rename = actions.add_parser("rename", help="give a map a new name")
    rename.add_argument("name", help="the map")
    rename.add_argument("new_name", metavar="NEW", help="its new name (1-64 of A-Z a-z 0-9 . _ -)")
    for sub, func in ((delete, run_delete), (restore, run_restore), (rename, run_rename)):
        _common(sub, default=argparse.SUPPRESS)  # given after the action or before it, on the command
        sub.set_defaults(func=func)


def run(args: argparse.Namespace) -> int:
    """Print one line per map (or the contract's JSON)."""
    with open_database(args.db) as db, db.read() as conn:
        maps = list_maps(conn=conn, archived=args.archived)
    if args.json:
        emit_json({"maps": [m.as_dict() for m in maps]})
        return 0
    if not maps:
        sys.stdout.write("no archived maps\n" if args.archived else "no maps\n")
        return 0
    _print_table(maps)
    return 0


def _print_table(maps: list[MapSummary]) -> None:
    width = max(4, *(len(m.name) for m in maps))
    archived = any(m.archived_at is not None for m in maps)
    sys.stdout.write(
        f"{'name':<{width}}  sessions  templates  experiences    links  residual  off  merges (rejected, unverified)"
        f"{'  archived at' if archived else ''}\n"
    )
    for m in maps:
        health = f"{m.health['residual']:>8.2f}  {m.health['switched_off']:>3}" if m.health else f"{'-':>8}  {'-':>3}"
        merges = m.as_dict()["merges"]
        counts = f"{merges['applied']:>6} ({merges['rejected']}, {merges['unverified']})"
        tail = counts if m.archived_at is None else f"{counts:<30}  {m.archived_at.isoformat(timespec='seconds')}"
        sys.stdout.write(
            f"{m.name:<{width}}  {m.sessions:>8}  {m.templates:>9}  {m.experiences:>11}  {m.links:>7}  {health}  "
            f"{tail}\n"
        )


def run_delete(args: argparse.Namespace) -> int:
    """Archive the map, or with ``--purge`` delete an archived map for good."""
    with open_database(args.db) as db, db.write() as conn:
        if args.purge:
            outcome = purge_map(conn=conn, name=args.name)
            result: dict[str, Any] = outcome.as_dict()
        else:
            record = archive_map(conn=conn, name=args.name)
            assert record.archived_at is not None
            result = {"deleted": record.name, "archived_at": record.archived_at.isoformat(), "restorable": True}
    if args.purge:
        info(f"purged map {args.name!r}: {result['sessions']} session(s), {result['merge_events']} merge event(s)")
    else:
        info(f"deleted map {args.name!r} (archived: 'mapserver maps restore {args.name}' brings it back)")
    if args.json:
        emit_json(result)
    return 0


def run_restore(args: argparse.Namespace) -> int:
    """Bring an archived map back."""
    with open_database(args.db) as db, db.write() as conn:
        record = restore_map(conn=conn, name=args.name)
    info(f"restored map {record.name!r}")
    if args.json:
        emit_json({"restored": record.name})
    return 0


def run_rename(args: argparse.Namespace) -> int:
    """Rename a live map."""
    with open_database(args.db) as db, db.write() as conn:
        record = rename_map(conn=conn, name=args.name, new_name=args.new_name)
    info(f"renamed map {args.name!r} to {record.name!r}")
    if args.json:
        emit_json({"renamed": args.name, "name": record.name})
    return 0

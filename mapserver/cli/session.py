"""``mapserver session move NAME [--to MAP]``: take a session out of its merged map into a new map of its own."""

from __future__ import annotations

import argparse

from mapserver.atlas import undo
from mapserver.cli._output import emit_json, info
from mapserver.store import DEFAULT_DB_URL, open_database


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``session`` command and its ``move`` subcommand."""
    parser = subparsers.add_parser("session", help="manage a stored session (move it out of a merged map)")
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    move = actions.add_parser(
        "move", help="take a session out of its merged map into a new map of its own (undoing the merge that brought "
                     "it in); the rest of the map stays whole",
    )  # fmt: skip
    move.add_argument("name", metavar="SESSION", help="the session (see GET /v1/maps/{name})")
    move.add_argument("--to", metavar="MAP", help="the new map's name (default: the session's name, made unique)")
    move.add_argument("--db", default=DEFAULT_DB_URL, help=f"SQLAlchemy URL (default: {DEFAULT_DB_URL})")
    move.add_argument("--json", action="store_true", help="print the JSON result as the last line of stdout")
    move.set_defaults(func=run_move)


def run_move(args: argparse.Namespace) -> int:
    """Move the session and say where it and the rest of its map are now."""
    with open_database(args.db) as db:
        outcome = undo.move_session(db, session=args.name, map_name=args.to)
    info(
        f"session {outcome.session!r} moved to map {outcome.map!r} (merge event {outcome.event_id} undone); the rest "
        f"stays in map {outcome.rest!r}"
    )
    if outcome.frames is not None:
        info(f"session {outcome.session!r} keeps its first {outcome.frames} frames, those it had when it merged online")
    if args.json:
        emit_json({"moved": True, "session": outcome.session, "map": outcome.map, "rest": outcome.rest,
                   "event": outcome.event_id, "frames": outcome.frames})  # fmt: skip
    return 0

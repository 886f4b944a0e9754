"""``mapserver unmerge --db URL --event ID``: undo a merge event, restoring the maps as they were before it."""

from __future__ import annotations

import argparse

from mapserver.atlas import undo
from mapserver.cli._output import emit_json, info
from mapserver.store import DEFAULT_DB_URL, open_database


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``unmerge`` command."""
    parser = subparsers.add_parser("unmerge", help="undo a merge event, restoring the maps as they were before it")
    parser.add_argument("--db", default=DEFAULT_DB_URL, help=f"SQLAlchemy URL (default: {DEFAULT_DB_URL})")
    parser.add_argument("--event", type=int, required=True, help="the merge event (see GET /v1/maps/{name})")
    parser.add_argument(
        "--rewind", action="store_true",
        help="leave an online merge's session partial at its merge frame, to continue it by processing its log again "
             "(default: complete there, its map whole and mergeable)",
    )  # fmt: skip
    parser.add_argument("--json", action="store_true", help="print the JSON result as the last line of stdout")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Undo the event and say what was restored."""
    with open_database(args.db) as db:
        outcome = undo.unmerge(db, event_id=args.event, rewind=args.rewind)
    info(f"merge event {outcome.event_id} undone: restored map(s) {', '.join(map(repr, outcome.maps))}")
    if outcome.session_status == "partial":
        info(
            f"session {outcome.session_rewound!r} is back at frame {outcome.frames} (the merge frame): process its "
            f"log again to continue it, or `mapserver merge --redo {outcome.event_id}` to re-apply the merge"
        )
    elif outcome.session_rewound is not None:
        info(
            f"session {outcome.session_rewound!r} keeps its first {outcome.frames} frames (those before the merge) "
            f"as a whole map; `mapserver merge --redo {outcome.event_id}` brings the merged map back as it was"
        )
    if args.json:
        emit_json({"unmerged": True, "event": outcome.event_id, "maps": outcome.maps,
                   "session": outcome.session_rewound, "frames": outcome.frames,
                   "session_status": outcome.session_status})  # fmt: skip
    return 0

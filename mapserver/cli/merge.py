"""``mapserver merge --db URL --map A --into B [--confirm K] [--merge-evidence M]``: merge stored map A into B.

``--redo EVENT`` re-applies an undone merge event instead (its recorded match on its archived states).
"""

from __future__ import annotations

import argparse

from mapserver import atlas
from mapserver.atlas import undo
from mapserver.cli._output import emit_json, info
from mapserver.errors import InputError
from mapserver.store import DEFAULT_DB_URL, open_database


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``merge`` command."""
    parser = subparsers.add_parser(
        "merge", help="merge stored map A into stored map B when a confirmed template match exists (or redo a merge)"
    )
    parser.add_argument("--db", default=DEFAULT_DB_URL, help=f"SQLAlchemy URL (default: {DEFAULT_DB_URL})")
    parser.add_argument("--map", dest="source", help="map A, merged into B")
    parser.add_argument("--into", help="map B")
    parser.add_argument(
        "--confirm", type=int, metavar="K",
        help="consecutive matching templates of A needed (default: A's merge_confirm parameter; 1 = the paper)",
    )  # fmt: skip
    parser.add_argument(
        "--merge-evidence", type=float, metavar="M",
        help="metres of net agreeing views along A that the alignment needs (default: A's merge_evidence_m; "
             "-1: 4 spacings of B; 0: the confirmed match alone, the paper's rule)",
    )  # fmt: skip
    parser.add_argument(
        "--settle", action=argparse.BooleanOptionalAction, default=None,
        help="move the merged map to the fixed point of relaxation, robust check included (default: yes, unless a "
             "map holds poses imported from another tool's save, which then keep their saved poses)",
    )  # fmt: skip
    parser.add_argument("--redo", type=int, metavar="EVENT", help="re-apply an undone merge event instead")
    parser.add_argument("--json", action="store_true", help="print the JSON result as the last line of stdout")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Merge (or redo), then report the event and the map."""
    if args.redo is not None:
        if args.source or args.into or args.confirm is not None or args.merge_evidence is not None or (
            args.settle is not None
        ):
            msg = ("--redo EVENT takes no --map, --into, --confirm, --merge-evidence or --settle (the event says what "
                   "to merge)")
            raise InputError(msg)
        with open_database(args.db) as db:
            outcome = undo.redo_merge(db, event_id=args.redo)
        info(f"merge event {outcome.event_id} applied again: map {outcome.map_name!r} ({', '.join(outcome.sessions)})")
    else:
        if not args.source or not args.into:
            msg = "merge needs --map A and --into B (or --redo EVENT)"
            raise InputError(msg)
        with open_database(args.db) as db:
            outcome = atlas.merge_stored_maps(
                db, source=args.source, into=args.into, confirm=args.confirm, evidence_m=args.merge_evidence,
                settle=args.settle,
            )
        r = outcome.record
        assert r is not None  # a merge always has its record; only a redo may restore an archive instead
        info(
            f"merged map {args.source!r} into {args.into!r}: event {outcome.event_id}, map {outcome.map_name!r} "
            f"({r.confirmations} confirming templates, {r.templates} templates, {r.experiences} experiences)"
        )
    if args.json:
        emit_json({"merged": True, "event": outcome.event_id, "map": outcome.map_name, "settled": outcome.settled})
    return 0

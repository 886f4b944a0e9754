"""``mapserver link --db URL --map A --from ID --to ID [--to-map B] [--transform DX,DY,DZ,DYAW]``: a manual link.

Joins two experiences as the same place (or with the stated transform: the pose of ``--to`` in ``--from``'s
frame). Within one map the link is added and checked by the robust relaxation; with ``--to-map B`` map B is
merged into map A through it (:mod:`mapserver.atlas.manual_links`). Undo it with ``mapserver unmerge --event ID``.
"""

from __future__ import annotations

import argparse
import getpass
import math

from mapserver.atlas.manual_links import LinkRequest, link_experiences
from mapserver.cli._output import emit_json, info
from mapserver.errors import InputError
from mapserver.store import DEFAULT_DB_URL, open_database


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``link`` command."""
    parser = subparsers.add_parser(
        "link", help="join two experiences by hand (the same place, or a stated transform); undo with unmerge"
    )
    parser.add_argument("--db", default=DEFAULT_DB_URL, help=f"SQLAlchemy URL (default: {DEFAULT_DB_URL})")
    parser.add_argument("--map", dest="map_name", required=True, help="map A, which holds experience --from")
    parser.add_argument("--from", dest="source", type=int, required=True, help="experience id in map A")
    parser.add_argument("--to", dest="target", type=int, required=True, help="experience id in map A (or --to-map)")
    parser.add_argument("--to-map", help="map B, which holds experience --to: B is merged into A through the link")
    parser.add_argument(
        "--transform", default="0,0,0,0", metavar="DX,DY,DZ,DYAW",
        help="the pose of --to in --from's frame, metres and radians (default 0,0,0,0: the same place, same heading)",
    )  # fmt: skip
    parser.add_argument("--author", help="who adds the link (default: the operating-system user)")
    parser.add_argument("--json", action="store_true", help="print the JSON result as the last line of stdout")
    parser.set_defaults(func=run)


def parse_transform(text: str) -> tuple[float, float, float, float]:
    """Return ``DX,DY,DZ,DYAW`` as four finite floats (InputError otherwise)."""
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        msg = f"--transform takes four finite numbers DX,DY,DZ,DYAW (metres, radians), got {text!r}"
        raise InputError(msg)
    return values[0], values[1], values[2], values[3]


def _os_user() -> str:
    try:
        return getpass.getuser()
    except (KeyError, OSError):  # no user name in the environment nor in the password database
        return "unknown"


def run(args: argparse.Namespace) -> int:
    """Add the link and say what the robust check made of it."""
    request = LinkRequest(
        map_name=args.map_name, from_id=args.source, to_id=args.target, to_map=args.to_map,
        transform=parse_transform(args.transform), author=args.author if args.author is not None else _os_user(),
    )  # fmt: skip
    with open_database(args.db) as db:
        outcome = link_experiences(db, request)
    joined = f" (map(s) {', '.join(map(repr, outcome.merged))} merged into it)" if outcome.merged else ""
    info(f"manual link {outcome.from_id} → {outcome.to_id} in map {outcome.map_name!r}{joined}: event "
         f"{outcome.event_id}, by {outcome.author}")  # fmt: skip
    if not outcome.active:
        info(f"FLAGGED: {outcome.as_dict()['reason']}; `mapserver unmerge --event {outcome.event_id}` removes it")
    if args.json:
        emit_json(outcome.as_dict())
    return 0

"""``mapserver export --db URL --map NAME --format json|tum|png|g2o|csv --out FILE``: write a stored map."""

from __future__ import annotations

import argparse

from mapserver.cli._output import emit_json, info
from mapserver.store import DEFAULT_DB_URL, open_database
from mapserver.store.export import EXPORT_FORMATS, export_map


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``export`` command."""
    parser = subparsers.add_parser(
        "export", help="write a stored map as map JSON, TUM poses, a PNG plot, a g2o pose graph or CSV tables"
    )
    parser.add_argument("--db", default=DEFAULT_DB_URL, help=f"SQLAlchemy URL (default: {DEFAULT_DB_URL})")
    parser.add_argument("--map", dest="map_name", required=True, help="the stored map")
    parser.add_argument("--format", dest="fmt", required=True, choices=EXPORT_FORMATS)
    parser.add_argument("--out", required=True, help="output file (written atomically)")
    parser.add_argument("--json", action="store_true", help="print the JSON result as the last line of stdout")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Export the map."""
    with open_database(args.db) as db:
        result = export_map(db, name=args.map_name, fmt=args.fmt, out=args.out)
    info(f"wrote map {args.map_name!r} ({result['experiences']} experiences) as {args.fmt} to {args.out}")
    if "links_out" in result:
        info(f"wrote its links to {result['links_out']}")
    if args.json:
        emit_json(result)
    return 0

"""``mapserver import DIR --db URL --format multisession-ratslam --map NAME``: store a map saved by another tool."""

from __future__ import annotations

import argparse

from mapserver.cli._output import emit_json, info
from mapserver.params import resolve_params
from mapserver.store import DEFAULT_DB_URL, open_database
from mapserver.store.import_msr import FORMAT, import_multisession_ratslam

FORMATS = (FORMAT,)


def register(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add the ``import`` command."""
    parser = subparsers.add_parser("import", help="store a map saved by another tool")
    parser.add_argument("directory", help="the saved map (multisession-ratslam: its Saves/<name> directory)")
    parser.add_argument("--db", default=DEFAULT_DB_URL, help=f"SQLAlchemy URL (default: {DEFAULT_DB_URL})")
    parser.add_argument("--format", dest="fmt", required=True, choices=FORMATS)
    parser.add_argument("--map", dest="map_name", required=True, help="name of the new map")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--preset", help="the parameters the map was built with (preset name)")
    group.add_argument("--config", help="the parameters the map was built with (config file)")
    parser.add_argument("--json", action="store_true", help="print the JSON result as the last line of stdout")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Import the directory as a new map."""
    params = resolve_params(args.preset, args.config, None)
    with open_database(args.db) as db:
        result = import_multisession_ratslam(db, directory=args.directory, map_name=args.map_name, params=params)
    info(
        f"imported {args.directory} as map {result.map!r}: {result.templates} templates, "
        f"{result.experiences} experiences, {result.links} links"
    )
    for note in result.notes:
        info(f"note: {note}")
    if args.json:
        emit_json(result.summary())
    return 0

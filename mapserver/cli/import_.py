"""``mapserver import PATH --db URL --format multisession-ratslam|g2o --map NAME``: load another tool's file.

* ``multisession-ratslam``: PATH is a save directory; it becomes a new map NAME (``--preset``/``--config``:
  the parameters it was built with).
* ``g2o``: PATH is a g2o file (e.g. an exported map optimised with g2o or GTSAM); its vertices become the
  experience poses of the stored map NAME (:mod:`mapserver.store.import_g2o`).
"""

from __future__ import annotations

import argparse

from mapserver.cli._output import emit_json, info
from mapserver.errors import InputError
from mapserver.params import resolve_params
from mapserver.store import DEFAULT_DB_URL, open_database
from mapserver.store.import_g2o import FORMAT as G2O
from mapserver.store.import_g2o import import_g2o_poses
from mapserver.store.import_msr import FORMAT, import_multisession_ratslam

FORMATS = (FORMAT, G2O)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``import`` command."""
    parser = subparsers.add_parser("import", help="store a map saved by another tool, or poses optimised by one")
    parser.add_argument(
        "directory", metavar="PATH",
        help="multisession-ratslam: its Saves/<name> directory; g2o: the .g2o file (poses of map --map)",
    )  # fmt: skip
    parser.add_argument("--db", default=DEFAULT_DB_URL, help=f"SQLAlchemy URL (default: {DEFAULT_DB_URL})")
    parser.add_argument("--format", dest="fmt", required=True, choices=FORMATS)
    parser.add_argument(
        "--map", dest="map_name", required=True,
        help="multisession-ratslam: name of the new map; g2o: the stored map whose poses the file holds",
    )  # fmt: skip
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--preset", help="the parameters the map was built with (preset name)")
    group.add_argument("--config", help="the parameters the map was built with (config file)")
    parser.add_argument(
        "--settle", action="store_true",
        help="multisession-ratslam: move the map to the fixed point of relaxation over its links, robust check "
             "included (default: keep the poses the tool saved)",
    )  # fmt: skip
    parser.add_argument("--json", action="store_true", help="print the JSON result as the last line of stdout")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Import the directory as a new map, or the g2o file's poses into a stored map."""
    if args.fmt == G2O:
        if args.preset or args.config or args.settle:
            msg = "--format g2o takes no --preset, --config or --settle (the stored map keeps its parameters)"
            raise InputError(msg)
        with open_database(args.db) as db:
            poses = import_g2o_poses(db, path=args.directory, map_name=args.map_name)
        info(
            f"set the poses of map {poses.map!r} from {args.directory}: {poses.experiences} experiences, "
            f"largest move {poses.max_shift_m:.6g} m"
        )
        summary = poses.summary()
    else:
        params = resolve_params(args.preset, args.config, None)
        with open_database(args.db) as db:
            result = import_multisession_ratslam(
                db, directory=args.directory, map_name=args.map_name, params=params, settle=args.settle
            )
        info(
            f"imported {args.directory} as map {result.map!r}: {result.templates} templates, "
            f"{result.experiences} experiences, {result.links} links"
        )
        summary = result.summary()
    for note in summary["notes"]:
        info(f"note: {note}")
    if args.json:
        emit_json(summary)
    return 0

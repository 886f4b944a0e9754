"""``mapserver path --db URL --map NAME --from ID --to ID [--weight time|distance]``: shortest path over a map."""

from __future__ import annotations

import argparse

from core.paths import ExperienceGraph, NoPath
from mapserver.cli._output import emit_json, info
from mapserver.errors import ConflictError, NotFoundError
from mapserver.store import DEFAULT_DB_URL, get_map, open_database
from mapserver.store.queries import load_graph


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``path`` command."""
    parser = subparsers.add_parser("path", help="shortest path between two experiences of a stored map")
    parser.add_argument("--db", default=DEFAULT_DB_URL, help=f"SQLAlchemy URL (default: {DEFAULT_DB_URL})")
    parser.add_argument("--map", dest="map_name", required=True, help="the stored map")
    parser.add_argument("--from", dest="source", type=int, required=True, help="experience id")
    parser.add_argument("--to", dest="target", type=int, required=True, help="experience id")
    parser.add_argument("--weight", choices=("time", "distance"), default="time", help="link cost (default: time)")
    parser.add_argument("--json", action="store_true", help="print the JSON result as the last line of stdout")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Find the path and print it."""
    with open_database(args.db) as db, db.read() as conn:
        record = get_map(conn=conn, name=args.map_name)
        graph = load_graph(conn=conn, map_id=record.id)
    size = graph.poses.shape[0]
    for node in (args.source, args.target):
        if not 0 <= node < size:
            msg = f"experience {node} does not exist in map {args.map_name!r} (it has {size})"
            raise NotFoundError(msg)
    paths = ExperienceGraph(graph.poses, graph.link_from, graph.link_to, graph.link_dt, graph.link_distance)
    found = paths.shortest_path(args.source, args.target, args.weight)
    if isinstance(found, NoPath):
        msg = f"no path from experience {args.source} to {args.target} in map {args.map_name!r}"
        raise ConflictError(msg)
    info(f"{len(found.nodes)} experiences, cost {found.cost:.3f} ({args.weight})")
    if args.json:
        emit_json({"nodes": [int(n) for n in found.nodes], "cost": float(found.cost), "weight": found.weight})
    else:
        print(" ".join(str(int(n)) for n in found.nodes))
    return 0

"""``mapserver ground-truth SESSION [GT.tum] --db URL [--out FILE]``: a stored session's ground truth.

With ``GT.tum`` the file becomes the session's ground truth (decimated as ``process`` keeps a log's ground-truth
topic, replacing what was kept); with ``--out`` the stored ground truth is written as a TUM file. The viewer
draws it over the map with the session's APE (``GET /v1/maps/{name}/ground-truth``).
"""

from __future__ import annotations

import argparse

import numpy as np

from mapserver.cli._output import emit_json, info
from mapserver.errors import InputError, NotFoundError
from mapserver.formats import read_tum, write_tum
from mapserver.store import DEFAULT_DB_URL, open_database
from mapserver.store.ground_truth import get_ground_truth, session_id_by_name, set_ground_truth


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``ground-truth`` command."""
    parser = subparsers.add_parser(
        "ground-truth", help="give a stored session ground truth (TUM), or write what it has",
        description="Store GT.tum as the session's ground truth (decimated to one pose per 0.1 s, replacing what "
        "was kept); with --out, write the session's stored ground truth as a TUM file.",
    )  # fmt: skip
    parser.add_argument("session", help="the stored session's name")
    parser.add_argument("ground_truth", nargs="?", metavar="GT.tum", help="ground truth to store (TUM format)")
    parser.add_argument("--db", default=DEFAULT_DB_URL, help=f"SQLAlchemy URL (default: {DEFAULT_DB_URL})")
    parser.add_argument("--out", metavar="FILE", help="write the stored ground truth here (TUM format)")
    parser.add_argument("--json", action="store_true", help="print the JSON result as the last line of stdout")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Store the ground truth and/or write it out; print ``{"session", "rows", "stored", "out"}`` with ``--json``."""
    if args.ground_truth is None and args.out is None:
        msg = "give GT.tum to store, --out FILE to write the stored ground truth, or both"
        raise InputError(msg)
    given = read_tum(args.ground_truth) if args.ground_truth is not None else None
    with open_database(args.db) as db:
        if given is not None:
            with db.write() as conn:
                sid = session_id_by_name(conn=conn, name=args.session)
                rows = np.hstack([given.stamps_s[:, None], given.positions_xyz, given.quat_xyzw])
                kept = set_ground_truth(conn=conn, session_id=sid, rows=rows)
            info(f"session {args.session!r}: {kept} ground-truth poses stored (of {len(given)})")
        with db.read() as conn:
            stored = get_ground_truth(conn=conn, session_id=session_id_by_name(conn=conn, name=args.session))
    if stored is None:
        msg = f"session {args.session!r} has no ground truth"
        raise NotFoundError(msg)
    if args.out is not None:
        write_tum(args.out, stored[:, 0], stored[:, 1:4], stored[:, 4:8])
        info(f"wrote {stored.shape[0]} ground-truth poses to {args.out}")
    if args.json:
        emit_json({"session": args.session, "rows": None if given is None else len(given),
                   "stored": int(stored.shape[0]), "out": args.out})  # fmt: skip
    return 0

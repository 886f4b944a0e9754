"""``mapserver report MAP_OR_SESSION --db URL --out DIR``: a self-contained HTML report (+ PNGs)."""

from __future__ import annotations

import argparse
from pathlib import Path

from mapserver.cli._output import emit_json, info
from mapserver.errors import InputError
from mapserver.store import DEFAULT_DB_URL, open_database


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``report`` command."""
    parser = subparsers.add_parser(
        "report",
        help="write a self-contained HTML report (+ PNGs) of a stored map or session",
        description=(
            "Map drawn to scale with loop closures and merges, template/experience activation timeline, "
            "trajectory against ground truth and APE/Hausdorff (from --ground-truth, --log, or the log the "
            "server kept for the session)."
        ),
    )
    parser.add_argument("target", metavar="MAP_OR_SESSION", help="a stored map's or session's name")
    parser.add_argument("--db", default=DEFAULT_DB_URL, help=f"SQLAlchemy URL (default: {DEFAULT_DB_URL})")
    parser.add_argument("--out", required=True, type=Path, help="output directory (created)")
    parser.add_argument("--ground-truth", action="append", default=[], metavar="[SESSION=]GT.tum",
                        help="ground truth of a session (TUM); repeatable")  # fmt: skip
    parser.add_argument("--log", action="append", default=[], metavar="[SESSION=]LOG",
                        help="a session's log with a ground-truth topic; repeatable")  # fmt: skip
    parser.add_argument("--json", action="store_true", help="print the JSON result as the last line of stdout")
    parser.set_defaults(func=run)


def _keyed(values: list[str], flag: str) -> dict[str | None, Path]:
    """Parse ``[SESSION=]PATH`` values; every path must exist."""
    out: dict[str | None, Path] = {}
    for value in values:
        key, sep, path = value.partition("=")
        session, file = (key, Path(path)) if sep and not Path(value).exists() else (None, Path(value))
        if not file.exists():
            msg = f"{flag} {value!r}: file not found"
            raise InputError(msg)
        out[session] = file
    return out


def run(args: argparse.Namespace) -> int:
    """Gather the map or session and write its report."""
    from mapserver.formats import read_tum
    from mapserver.report import gather, write_report

    truths = {k: read_tum(v) for k, v in _keyed(args.ground_truth, "--ground-truth").items()}
    logs = _keyed(args.log, "--log")
    with open_database(args.db, upgrade=False) as db:
        inputs = gather(db, args.target, ground_truth=truths, logs=logs)
    result = write_report(inputs, args.out)
    for session, ev in result["evaluation"].items():
        if "ape_rmse" in ev:
            rpe = ", ".join(f"RPE per {r['delta_m']:g} m {r['trans_rmse']:.3f} m" for r in ev["rpe"]
                            if r["trans_rmse"] is not None)  # fmt: skip
            info(f"{session}: APE RMSE {ev['ape_rmse']:.3f} m, Hausdorff {ev['hausdorff']:.3f} m"
                 + (f", {rpe}" if rpe else ""))  # fmt: skip
    info(f"wrote {result['report']} ({len(result['pngs'])} figures)")
    if args.json:
        emit_json(result)
    return 0

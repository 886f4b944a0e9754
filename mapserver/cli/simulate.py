"""``mapserver simulate SCENARIO --out DIR``: synthetic mission logs with ground truth."""

from __future__ import annotations

import argparse
import math
from typing import Any

from mapserver.cli._output import emit_json, info
from mapserver.cli._progress import progress_bar
from mapserver.errors import InputError
from mapserver.ingest.simulator import SCENARIOS, simulate
from mapserver.pairs import parse_pairs


def _epilog() -> str:
    lines = ["scenarios (parameters with defaults, set with --param NAME=VALUE):"]
    for definition in SCENARIOS.values():
        params = ", ".join(f"{k}={v:g}" for k, v in definition.defaults.items())
        lines.append(f"  {definition.name:<8} {definition.description} [{params}]")
    return "\n".join(lines)


def register(subparsers: Any) -> None:
    """Add the ``simulate`` command to the CLI."""
    parser = subparsers.add_parser(
        "simulate",
        help="write synthetic mission logs and ground truth for a named scenario",
        description=(
            "Simulate a scenario: render a textured 3-D world from a panoramic camera along the vehicle's "
            "path, with drifting odometry and ground truth, and write each session as a log "
            "(/robot/camera/image, /robot/odom, /robot/ground_truth) plus a TUM ground-truth file. "
            "DIR/scenario.json holds the same JSON as --json prints; its 'preset' names the engine preset "
            "that suits the logs. Deterministic per seed."
        ),
        epilog=_epilog(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("scenario", metavar="SCENARIO", help=f"one of: {', '.join(SCENARIOS)}")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory (created)")
    parser.add_argument("--seed", type=int, default=0, metavar="N", help="random seed (default 0)")
    parser.add_argument(
        "--format", dest="fmt", default="bag", metavar="FMT", help="bag (ROS 1), db3 or mcap (ROS 2); default bag"
    )
    parser.add_argument(
        "--scale", type=float, default=1.0, metavar="F", help="route and world size factor (default 1)"
    )
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="scenario parameter (repeatable or comma-separated), e.g. heading_offset_deg=90 for ellipse",
    )
    parser.add_argument("--json", action="store_true", help="print the result as JSON on the last stdout line")
    parser.set_defaults(func=run)


def parse_params(items: list[str]) -> dict[str, float]:
    """Parse ``--param`` values (``NAME=VALUE``, repeatable, comma-separated) into numbers.

    Raises:
        InputError: an entry without ``=``, a repeated name or a value that is not a finite number.
    """
    params: dict[str, float] = {}
    for name, value in parse_pairs(items, flag="--param", form="NAME=VALUE", example="laps=2").items():
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if not math.isfinite(number):
            msg = f"bad --param {name}={value}: {value!r} is not a finite number"
            raise InputError(msg)
        params[name] = number
    return params


def run(args: argparse.Namespace) -> int:
    """Simulate the scenario; print a summary (stderr) and, with ``--json``, the scenario JSON (stdout)."""
    params = parse_params(args.param)
    if args.scenario not in SCENARIOS:
        msg = f"unknown scenario {args.scenario!r} (valid: {', '.join(SCENARIOS)})"
        raise InputError(msg)
    update, close = progress_bar(f"simulating {args.scenario}")
    try:
        document = simulate(
            args.scenario, args.out, seed=args.seed, fmt=args.fmt, scale=args.scale, params=params, progress=update
        )
    finally:
        close()
    logs = [*document["sessions"]]
    if document["single"] is not None and all(s["log"] != document["single"]["log"] for s in logs):
        logs.append({"name": "single", **document["single"]})
    for entry in logs:
        info(f"{args.out}/{entry['log']}: {entry['frames']} frames, {entry['duration_s']:.1f} s ({entry['name']})")
    info(f"preset: {document['preset']}  (scenario.json written to {args.out})")
    if args.json:
        emit_json(document)
    return 0

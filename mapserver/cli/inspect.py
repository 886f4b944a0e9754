"""``mapserver inspect LOG``: every topic (type, count, rate, span) and the topic mapping ``process`` would use.

A log ``process`` could not use is listed all the same (exit 0), with what is missing.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from mapserver.cli._output import emit_json
from mapserver.ingest import parse_topics_arg
from mapserver.ingest.survey import survey_log


def register(subparsers: Any) -> None:
    """Add the ``inspect`` command to the CLI."""
    parser = subparsers.add_parser(
        "inspect",
        help="list a log's topics and the topic mapping 'process' would use",
        description=(
            "Open a mission log (ROS 1 .bag, ROS 2 bag directory, standalone .db3 or .mcap), list every topic "
            "with type, message count, rate and time span (bag time), and show the topic mapping that "
            "'process' would use: image = the Image/CompressedImage topic with the most messages; odometry = "
            "the nav_msgs/Odometry topic with the most messages whose name is not ground-truth-like; "
            "ground_truth = the ground-truth-like Odometry/Pose topic, else the only PoseStamped topic. "
            "A log that 'process' cannot use (no camera topic, undecodable images) is still listed, with "
            "what is missing; the exit code is 0 for any readable log."
        ),
    )
    parser.add_argument("log", metavar="LOG", help="mission log: .bag, .db3, .mcap or a ROS 2 bag directory")
    parser.add_argument(
        "--topics",
        metavar="K=V,...",
        help="override the mapping, keys image, odometry, ground_truth (e.g. image=/cam/image,odometry=none)",
    )
    parser.add_argument("--json", action="store_true", help="print the result as JSON on the last stdout line")
    parser.set_defaults(func=run)


def _row(topic: dict[str, Any]) -> tuple[str, str, str, str, str]:
    span = "-" if topic["first_s"] is None else f"{topic['first_s']:.2f}–{topic['last_s']:.2f}"
    return (topic["name"], topic["type"], str(topic["count"]), f"{topic['rate_hz']:.2f}", span)


def format_table(result: dict[str, Any]) -> str:
    """Render the ``inspect`` result as a human-readable table (topics, mapping, missing roles, notes)."""
    rows = [("topic", "type", "count", "rate (Hz)", "span (s)")]
    rows += [_row(t) for t in result["topics"]]
    widths = [max(len(r[i]) for r in rows) for i in range(5)]
    lines = [f"log: {result['log']}  ({result['duration_s']:.2f} s, {result['frames']} frames)", ""]
    for i, row in enumerate(rows):
        left = [f"{row[k]:<{widths[k]}}" for k in (0, 1)]
        right = [f"{row[k]:>{widths[k]}}" for k in (2, 3, 4)]
        lines.append("  ".join(left + right))
        if i == 0:
            lines.append("  ".join("-" * w for w in widths))
    lines += ["", "mapping:"]
    for key, value in result["mapping"].items():
        suffix = f"  ({result['odometry_mode']})" if key == "odometry" and value and result["odometry_mode"] else ""
        lines.append(f"  {key:<12} {value if value is not None else '-'}{suffix}")
    lines.append("")
    if result["usable"]:
        lines.append("usable by process: yes")
    else:
        lines.append(f"usable by process: no (missing: {', '.join(result['missing']) or '-'})")
        lines += [f"  {role}: {reason}" for role, reason in result["reasons"].items()]
    lines += [f"note: {note}" for note in result["notes"]]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Inspect the log; the table goes to stdout, or to stderr with ``--json`` (JSON on stdout)."""
    overrides = parse_topics_arg(args.topics) if args.topics else None
    result = survey_log(args.log, overrides).as_dict()
    table = format_table(result)
    if args.json:
        sys.stderr.write(table + "\n")
        sys.stderr.flush()
        emit_json(result)
    else:
        sys.stdout.write(table + "\n")
        sys.stdout.flush()
    return 0

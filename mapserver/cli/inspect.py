"""``mapserver inspect LOG``: topics, types, counts, rates and the topic mapping ``process`` would use."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from mapserver.cli._output import emit_json
from mapserver.ingest import MissionLog, open_log, parse_topics_arg


def register(subparsers: Any) -> None:
    """Add the ``inspect`` command to the CLI."""
    parser = subparsers.add_parser(
        "inspect",
        help="list a log's topics and the topic mapping 'process' would use",
        description=(
            "Open a mission log (ROS 1 .bag, ROS 2 bag directory, standalone .db3 or .mcap), list its topics "
            "with type, message count and mean rate, and show the topic mapping that 'process' would use: "
            "image = the Image/CompressedImage topic with the most messages; odometry = the "
            "nav_msgs/Odometry topic with the most messages whose name is not ground-truth-like; "
            "ground_truth = the ground-truth-like Odometry/Pose topic, else the only PoseStamped topic."
        ),
    )
    parser.add_argument("log", metavar="LOG", help="mission log: .bag, .db3, .mcap or a ROS 2 bag directory")
    parser.add_argument(
        "--topics",
        metavar="K=V,...",
        help="override the mapping, keys image, odometry, ground_truth (e.g. image=/cam/image,odometry=none)",
    )
    parser.add_argument(
        "--json", action="store_true", help="print the result as JSON on the last stdout line"
    )
    parser.set_defaults(func=run)


def describe(log: MissionLog) -> dict[str, Any]:
    """Return the ``inspect`` result object of an open log."""
    return {
        "log": str(log.path),
        "topics": [
            {"name": t.name, "type": t.msgtype, "count": t.count, "rate_hz": round(t.rate_hz, 3)}
            for t in log.topics
        ],
        "mapping": log.mapping.as_dict(),
        "odometry_mode": log.odometry_mode,
        "frames": log.count_frames(),
        "duration_s": round(log.duration_s, 6),
    }


def format_table(result: dict[str, Any]) -> str:
    """Render the ``inspect`` result as a human-readable table."""
    rows = [("topic", "type", "count", "rate (Hz)")]
    rows += [(t["name"], t["type"], str(t["count"]), f"{t['rate_hz']:.2f}") for t in result["topics"]]
    widths = [max(len(r[i]) for r in rows) for i in range(4)]
    lines = [f"log: {result['log']}  ({result['duration_s']:.2f} s, {result['frames']} frames)", ""]
    for i, row in enumerate(rows):
        lines.append(
            f"{row[0]:<{widths[0]}}  {row[1]:<{widths[1]}}  {row[2]:>{widths[2]}}  {row[3]:>{widths[3]}}"
        )
        if i == 0:
            lines.append("  ".join("-" * w for w in widths))
    lines.append("")
    lines.append("mapping:")
    for key, value in result["mapping"].items():
        suffix = f"  ({result['odometry_mode']})" if key == "odometry" and value else ""
        lines.append(f"  {key:<12} {value if value is not None else '-'}{suffix}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Inspect the log; the table goes to stdout, or to stderr with ``--json`` (JSON on stdout)."""
    overrides = parse_topics_arg(args.topics) if args.topics else None
    with open_log(args.log, overrides) as log:
        result = describe(log)
    table = format_table(result)
    if args.json:
        sys.stderr.write(table + "\n")
        sys.stderr.flush()
        emit_json(result)
    else:
        sys.stdout.write(table + "\n")
        sys.stdout.flush()
    return 0

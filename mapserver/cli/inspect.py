"""``mapserver inspect LOG``: a log's topics, the mapping ``process`` would use, the preset and settings it decides.

Every topic (type, count, rate, span); the settings: :mod:`mapserver.ingest.recommend`. A log ``process`` could
not use is listed all the same (exit 0), with what is missing.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from mapserver.cli._output import emit_json
from mapserver.errors import InputError
from mapserver.ingest import parse_topics_arg
from mapserver.ingest.recommend import NEED_TEXTS, Recommendation, recommend
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
            "what is missing; the exit code is 0 for any readable log. For a usable log it recommends a preset "
            "(circle for a 360° camera, forward otherwise) and the settings the log decides (field of view, "
            "camera rate, template size, panoramic matching) as a --set argument and an INI file."
        ),
    )
    parser.add_argument("log", metavar="LOG", help="mission log: .bag, .db3, .mcap or a ROS 2 bag directory")
    parser.add_argument(
        "--topics",
        metavar="K=V,...",
        help="override the mapping, keys image, odometry, ground_truth, sonar, dvl, imu, depth "
        "(e.g. image=/cam/image,odometry=none)",
    )
    parser.add_argument(
        "--fov",
        type=float,
        metavar="DEG",
        help="the camera's horizontal field of view in degrees (0 < DEG <= 360; wins over a CameraInfo topic's)",
    )
    parser.add_argument("--ini", metavar="FILE", help="also write the recommended parameters as an INI (--config)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON on the last stdout line")
    parser.set_defaults(func=run)


def _check_fov(value: float | None) -> float | None:
    if value is not None and not (math.isfinite(value) and 0.0 < value <= 360.0):
        msg = f"--fov must be a field of view in degrees, 0 < DEG <= 360, got {value!r}"
        raise InputError(msg)
    return value


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
    motion = {"odometry": "odometry", "navigation": "navigation fusion (dvl + imu + depth)"}
    lines.append(f"  {'motion':<12} {motion.get(result.get('motion') or '', 'visual odometry')}")
    lines.append("")
    if result["usable"]:
        lines.append("usable by process: yes")
    else:
        lines.append(f"usable by process: no (missing: {', '.join(result['missing']) or '-'})")
        lines += [f"  {role}: {reason}" for role, reason in result["reasons"].items()]
    lines += [f"note: {note}" for note in result["notes"]]
    return "\n".join(lines)


def format_recommendation(rec: Recommendation, log: str) -> str:
    """Render the recommendation: the camera as the log shows it, the ``process`` command, the INI."""
    cam = rec.camera
    fov = "unknown" if cam["fov_deg"] is None else f"{cam['fov_deg']:g}° (from {cam['fov_source']})"
    odometry = "none" if cam["odometry_hz"] is None else f"{cam['odometry_hz']:.2f} Hz"
    kind = "panoramic (360°)" if cam["panoramic"] else "forward"
    lines = [
        "",
        f"camera: {cam['width']}×{cam['height']} px, {kind}, field of view {fov}; "
        f"camera {cam['camera_hz']:.2f} Hz, odometry {odometry}",
        f"recommended: preset {rec.preset}",
        f"  mapserver process {log} --preset {rec.preset} --set {rec.set_argument()}",
        "  or as an INI for --config:",
    ]
    lines += [f"    {line}" for line in rec.ini().splitlines()]
    lines += [f"{'need' if note in NEED_TEXTS.values() else 'note'}: {note}" for note in rec.notes]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Inspect the log; the table goes to stdout, or to stderr with ``--json`` (JSON on stdout)."""
    overrides = parse_topics_arg(args.topics) if args.topics else None
    fov = _check_fov(args.fov)
    survey = survey_log(args.log, overrides)
    result = survey.as_dict()
    table = format_table(result)
    rec = recommend(survey, fov)
    result["recommendation"] = None if rec is None else rec.as_dict()
    if rec is not None:
        table += "\n" + format_recommendation(rec, args.log)
        if args.ini:
            Path(args.ini).write_text(rec.ini(), encoding="utf-8")
    if args.json:
        sys.stderr.write(table + "\n")
        sys.stderr.flush()
        emit_json(result)
    else:
        sys.stdout.write(table + "\n")
        sys.stdout.flush()
    return 0

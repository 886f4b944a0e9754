"""``mapserver evaluate MAP.json --ground-truth GT.tum``: accuracy of a map against ground truth."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from mapserver.cli._output import emit_json, info
from mapserver.errors import InputError
from mapserver.evaluation import RecognitionSettings, evaluate_map, place_recognition, plot_map_vs_ground_truth
from mapserver.formats import read_map_json, read_tum


def register(subparsers: Any) -> None:
    """Add the ``evaluate`` command to the CLI."""
    parser = subparsers.add_parser(
        "evaluate",
        help="accuracy of a map against ground truth (APE RMSE, Hausdorff)",
        description=(
            "Align the map's experiences rigidly to the ground truth (Umeyama 1991; planar maps in xy) and "
            "report the APE RMSE of their positions, the same for the raw odometry when known, and the "
            "symmetric Hausdorff distance between the aligned experiences and the ground truth. Maps written "
            "by 'process --out' also record each frame's template; from it come the place-recognition rates: "
            "revisit_frames (frames within R m of a frame more than T s earlier), revisit_match_rate (the "
            "share of those whose template was created more than T s earlier within R' m) and "
            "false_match_rate (the share of matching frames whose template was created more than F m away)."
        ),
    )
    parser.add_argument(
        "map", metavar="MAP.json", help="map JSON written by 'process' or 'export --format json'"
    )
    parser.add_argument("--ground-truth", required=True, metavar="GT.tum", help="ground truth, TUM format")
    parser.add_argument(
        "--json", action="store_true", help="print the result as JSON on the last stdout line"
    )
    parser.add_argument("--plot", metavar="PNG", help="also draw the aligned map over the ground truth")
    parser.add_argument(
        "--max-diff",
        type=float,
        default=0.05,
        metavar="S",
        help="accept stamps up to S seconds outside the ground truth's time span (default 0.05)",
    )
    parser.add_argument("--session", metavar="NAME", help="evaluate only this session's experiences")
    defaults = RecognitionSettings()
    parser.add_argument("--revisit-radius", type=float, default=defaults.revisit_radius, metavar="R",
                        help=f"revisit: within R m of an earlier frame (default {defaults.revisit_radius})")
    parser.add_argument("--revisit-gap", type=float, default=defaults.revisit_gap_s, metavar="T",
                        help=f"revisit: that frame more than T s earlier (default {defaults.revisit_gap_s})")
    parser.add_argument("--match-radius", type=float, default=defaults.match_radius, metavar="R2",
                        help=f"recognised: template created within R2 m (default {defaults.match_radius})")
    parser.add_argument("--false-radius", type=float, default=defaults.false_radius, metavar="F",
                        help=f"false match: template created more than F m away (default {defaults.false_radius})")
    parser.add_argument(
        "--odometry",
        metavar="ODOM.tum",
        help="raw odometry trajectory (TUM) for the baseline; default: the map's 'odometry' key if any",
    )
    parser.set_defaults(func=run)


def _positive(value: float, flag: str) -> float:
    if not math.isfinite(value) or value < 0.0:
        msg = f"{flag} must be a non-negative number, got {value!r}"
        raise InputError(msg)
    return float(value)


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.4f} m"


def run(args: argparse.Namespace) -> int:
    """Evaluate the map, print the summary (stderr) and, with ``--json``, the result (stdout)."""
    max_diff = float(args.max_diff)
    if not math.isfinite(max_diff) or max_diff < 0.0:
        msg = f"--max-diff must be a non-negative number of seconds, got {args.max_diff!r}"
        raise InputError(msg)
    doc = read_map_json(args.map)
    gt = read_tum(args.ground_truth)
    odometry = read_tum(args.odometry) if args.odometry else None
    if args.plot:
        plot_dir = Path(args.plot).resolve().parent
        if not plot_dir.is_dir():
            msg = f"directory of --plot does not exist: {str(plot_dir)!r}"
            raise InputError(msg)
    settings = RecognitionSettings(
        revisit_radius=_positive(args.revisit_radius, "--revisit-radius"),
        revisit_gap_s=_positive(args.revisit_gap, "--revisit-gap"),
        match_radius=_positive(args.match_radius, "--match-radius"),
        false_radius=_positive(args.false_radius, "--false-radius"),
    )
    result = evaluate_map(doc, gt, odometry=odometry, max_diff_s=max_diff, session=args.session)
    if doc.get("frames") and (args.session is None or len(doc.get("sessions", [])) <= 1):
        recognition = place_recognition(doc["frames"], gt, settings, max_diff_s=max_diff)
        result.update({k: v for k, v in recognition.items() if k != "settings"})
        result["recognition_settings"] = recognition["settings"]
    info(
        f"{args.map}: {result['experiences']} experiences, {result['aligned']} with ground truth "
        f"({len(gt)} poses), evaluated in {result['dims']}-D"
    )
    info(
        f"  APE RMSE (experiences): {_fmt(result['ape_rmse'])}  mean {_fmt(result['ape_mean'])}  "
        f"max {_fmt(result['ape_max'])}"
    )
    info(f"  APE RMSE (odometry):    {_fmt(result['odometry_ape_rmse'])}")
    info(f"  Hausdorff:              {_fmt(result['hausdorff'])}")
    for entry in result["rpe"]:
        label = f"RPE per {entry['delta_m']:g} m:"
        rotation = "n/a" if entry["rot_rmse_deg"] is None else f"{entry['rot_rmse_deg']:.2f} deg"
        info(f"  {label:<24}{_fmt(entry['trans_rmse'])}  rot {rotation} ({entry['pairs']} segments)")
    if result.get("ape_z_rmse") is not None:
        info(
            f"  z RMSE (experiences):   {_fmt(result['ape_z_rmse'])}  (odometry "
            f"{_fmt(result['odometry_ape_z_rmse'])})"
        )
    if "revisit_frames" in result:
        rate = result["revisit_match_rate"]
        false = result["false_match_rate"]
        info(
            f"  revisits: {result['revisit_frames']} frames, {result['revisit_matched']} recognised "
            f"({'n/a' if rate is None else f'{100 * rate:.1f} %'}); false matches "
            f"{result['false_matches']}/{result['matched_frames']} "
            f"({'n/a' if false is None else f'{100 * false:.1f} %'})"
        )
    if args.plot:
        plot_map_vs_ground_truth(
            doc, gt, args.plot, odometry=odometry, max_diff_s=max_diff, session=args.session
        )
        result["plot"] = str(args.plot)
        info(f"  plot written to {args.plot}")
    if args.json:
        emit_json(result)
    return 0

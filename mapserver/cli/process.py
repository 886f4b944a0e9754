"""``mapserver process LOG``: run the SLAM engine over one mission log.

Registering the command loads only the parameter presets; the engine, the log reader and the store load when
the command runs (``mapserver process --help`` answers without them).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from core.config import PRESETS, Params
from mapserver.cli._output import emit_json, info
from mapserver.errors import InputError


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``process`` command."""
    parser = subparsers.add_parser("process", help="run the SLAM engine over a mission log")
    parser.add_argument("log", help="ROS 1 .bag, ROS 2 bag directory, .db3 or .mcap")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--preset", help=f"parameter preset ({', '.join(PRESETS)})")
    group.add_argument("--config", help="OpenRatSLAM config_*.txt or OpenRatSLAM2 YAML file")
    parser.add_argument("--set", dest="settings", metavar="KEY=VALUE,...", action="append",
                        help="engine parameters on top of the preset or config, e.g. vt_shift_heading=1 "
                             "(repeatable: every --set applies)")
    parser.add_argument("--topics", help="topic overrides: image=/cam,odometry=/odom,ground_truth=/gt (none: off); "
                        "sonar=/t adds a sonar image topic (sdr-htm front-end); dvl=, imu=, depth= name the "
                        "navigation sensors fused when the log has no odometry")
    parser.add_argument("--out", help="write the map JSON here")
    parser.add_argument("--db", help="store the session in this database (SQLAlchemy URL)")
    parser.add_argument("--map", dest="map_name", help="name of the new map when the session connects to none")
    parser.add_argument("--no-merge", action="store_true", help="always keep the session a separate map")
    parser.add_argument("--into", metavar="MAP",
                        help="merge the session into this stored map only; refused, with nothing stored, when it "
                             "does not merge (excludes --map, --no-merge, --stop-after)")  # fmt: skip
    parser.add_argument(
        "--confirm", type=int, metavar="K",
        help="consecutive matching frames that confirm a merge (default: the parameters' merge_confirm; 1 = paper)",
    )  # fmt: skip
    parser.add_argument(
        "--merge-evidence", type=float, metavar="M",
        help="metres of net agreeing views a merge needs (parameter merge_evidence_m; -1: the map's scale; "
        "0: --confirm matches alone, the paper's trigger)",
    )  # fmt: skip
    parser.add_argument(
        "--merge-probation", type=float, metavar="M",
        help="metres a merge keeps verifying itself before it stands (parameter merge_probation_m; -1: the "
        "map's scale; 0: no verification)",
    )  # fmt: skip
    parser.add_argument(
        "--merge-no-shift", action="store_true",
        help="DEBUG: merge without operation (iii), the pose-cell lattice shift (Menezes et al. Fig. 12)",
    )  # fmt: skip
    parser.add_argument("--backbone", choices=("none", "shufflenetv2", "alexnet"),
                        help="CNN of the sdr-htm front-end (none: the weight-free encoder)")
    parser.add_argument("--weights", help="torchvision state-dict file of the --backbone (never downloaded)")
    parser.add_argument("--stop-after", type=int, help="process only this many frames (resume later with --db); "
                        "a merge then on probation is verified first: the run stops when its probation ends")
    parser.add_argument(
        "--max-image-pixels", type=int, metavar="N",
        help="refuse a frame of more than N pixels, read from its header before decoding (default: "
        "$MAPSERVER_MAX_IMAGE_PIXELS or 33554432)",
    )  # fmt: skip
    parser.add_argument("--json", action="store_true", help="print the JSON summary as the last line of stdout")
    parser.set_defaults(func=run)


def _check_into(args: argparse.Namespace) -> None:
    """Refuse ``--into`` with the flags it excludes (the pipeline words the same refusals for any caller)."""
    if args.into is None:
        return
    for given, flag in ((not args.db, "needs --db"), (args.map_name, "excludes --map"),
                        (args.no_merge, "excludes --no-merge"), (args.stop_after is not None, "excludes --stop-after")):
        if given:
            msg = f"--into {flag}"
            raise InputError(msg)


def run(args: argparse.Namespace) -> int:
    """Process the log and report the summary."""
    from mapserver.cli._progress import progress_bar
    from mapserver.ingest.topics import parse_topics_arg

    log = Path(args.log)
    if not log.exists():
        msg = f"log not found: {str(log)!r}"
        raise InputError(msg)
    params = _params(args, log)
    topics = parse_topics_arg(args.topics) if args.topics else None
    if args.map_name and not args.db:
        msg = "--map needs --db"
        raise InputError(msg)
    _check_into(args)
    if args.db:
        from mapserver.params import require_storable

        require_storable(params)
    if args.max_image_pixels is not None:
        from mapserver.ingest.decode import set_max_image_pixels

        set_max_image_pixels(args.max_image_pixels)
    update, close = progress_bar(f"processing {log.name}")
    try:
        if args.db:
            from mapserver.processing import pipeline

            result = pipeline.process_into_store(
                log,
                params,
                db_url=args.db,
                map_name=args.map_name,
                topics=topics,
                merge=not args.no_merge,
                stop_after=args.stop_after,
                out=args.out,
                progress=update,
                confirm=args.confirm,
                shift_lattice=not args.merge_no_shift,
                into=args.into,
            )
        else:
            if args.stop_after is not None:
                msg = "--stop-after needs --db (the stored state is what a later run resumes from)"
                raise InputError(msg)
            if args.confirm is not None or args.merge_no_shift:
                msg = "--confirm and --merge-no-shift need --db (merging is into stored maps)"
                raise InputError(msg)
            from mapserver.processing.run import process_log

            result = process_log(log, params, topics=topics, out=args.out, progress=update)
    finally:
        close()
    warning = None if result.dropped is None else result.dropped.warning()
    if warning is not None:
        info(f"warning: {warning}")
    _report(result.summary(), args.json)
    if not args.out and not args.db:
        info("warning: nothing was kept: give --out MAP.json to write the map, or --db URL to store it")
    return 0


def _params(args: argparse.Namespace, log: Path) -> Params:
    """Return the run's parameters: preset or config, ``--set``, the front-end options, the merge overrides."""
    from mapserver.params import resolve_params, with_frontend, with_settings

    params = with_settings(resolve_params(args.preset, args.config, log), ",".join(args.settings or []))
    params = with_frontend(params, args.backbone, args.weights)
    overrides = {"merge_evidence_m": args.merge_evidence, "merge_probation_m": args.merge_probation}
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if overrides:
        if not args.db:
            msg = "--merge-evidence and --merge-probation need --db (merging is into stored maps)"
            raise InputError(msg)
        params = params.replace(**overrides)
    return params


def _report(summary: dict[str, Any], as_json: bool) -> None:
    """Print the summary line (and the merges) on stderr; the JSON summary on stdout with ``--json``."""
    info(
        f"{summary['frames']} frames → {summary['templates']} templates, {summary['experiences']} experiences, "
        f"{summary['links']} links, {summary['loop_closures']} loop closures, {len(summary['merges'])} merges "
        f"in {summary['seconds']:.2f} s (map {summary['map']!r})"
    )
    for merge in summary["merges"]:
        info(
            f"merged into map {merge['into']!r} at frame {merge['frame']} (event {merge['event']}, "
            f"{merge['confirmations']} confirmations, {merge['matched_templates']} templates matched)"
        )
    if as_json:
        emit_json(summary)

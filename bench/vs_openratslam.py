"""Speed against OpenRatSLAM's C++ core on three long logs: ``mapserver process`` end to end vs the C++ SLAM only.

Usage (from the repository root; needs a local copy of davidmball/ratslam and Boost's headers, see
bench/differential/cxx.py)::

    PYTHONPATH=$PWD .venv/bin/python bench/vs_openratslam.py --ratslam /tmp/ratslam \
        [--logs matching,panoramic,light] [--runs 3] [--laps 8] [--work DIR] [--baseline CHECKOUT] [--set K=V]
    .venv/bin/python bench/vs_openratslam.py --write-only DIR [--logs light,matching] [--laps 8]

Every log is the simulator's ``loop`` scenario (``--laps`` laps, seed 0); they differ in what dominates a frame:

* ``matching``: a forward camera of 160×120 pixels at 5 Hz, raw mono8 images (issue 13's long mission,
  8 laps ≈ 5,500 frames), 60×20 patch-normalised templates that are rarely recognised, so the map grows
  to thousands of templates and comparing the view with them dominates;
* ``panoramic``: the ``circle`` preset's 360° camera (256×64 pixels at 1 Hz) and its parameters (80×80×35
  lattice, 128×32 templates): the pose cells dominate;
* ``light``: the forward camera again, JPEG-compressed, with templates that are recognised (no patch
  normalisation, ``vt_match_threshold`` 0.03): nearly every frame matches one of a few dozen templates and
  every part of a frame is cheap, so the fixed cost of a frame (reading, decoding, the per-frame Python)
  decides.

The parameters are written as an INI file that both engines read (mapserver's other parameters keep their
defaults). mapserver's figure is ``mapserver process LOG --config INI --out MAP`` timed as a subprocess:
start-up, bag reading, decoding, SLAM and writing the map. OpenRatSLAM's is the driver's SLAM loop alone,
frames decoded beforehand. Each run times both, one after the other, so that the machine's state is the same
for both; the ratio is (mapserver frames/s) / (OpenRatSLAM frames/s). The share of frames whose view matched
an existing template is printed for both engines, and the SHA-256 of the map's experience poses for every
run (a run-to-run check, and the evidence that a change left the map alone). ``--baseline CHECKOUT`` times a
second checkout's ``mapserver process`` (another commit, e.g. ``git worktree add /tmp/base main``) in every run
too, for a before/after in the same runs; ``--set KEY=VALUE,...`` passes engine parameters to mapserver alone
(a diagnostic: OpenRatSLAM has no such keys). Timings on a shared machine are noisy: compare runs made side by
side.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent / "differential"))

from cxx import CxxRun, FrameWriter, HarnessError, build_driver, run_driver, write_ini

from core import Params, preset
from mapserver.ingest.reader import open_log
from mapserver.ingest.simulator.output import plan_scenario, render_frames, simulate_session
from mapserver.ingest.simulator.render import Camera
from mapserver.ingest.simulator.scenarios import GROUND_CAMERA
from mapserver.ingest.writer import ImageEncoding, write_log

REPO = Path(__file__).resolve().parents[1]
PARAMS = Params().replace(
    template_x_size=60, template_y_size=20, vt_match_threshold=0.08, vt_patch_normalise=2, vt_shift_match=5,
    vt_step_match=1,
    pc_cell_x_size=0.25, exp_delta_pc_threshold=2.0, exp_loops=20, exp_initial_em_deg=0.0,
)
LIGHT_PARAMS = PARAMS.replace(vt_patch_normalise=0, vt_match_threshold=0.03)
FORWARD_CAMERA = Camera(
    width=160, height=120, hfov_deg=90.0, vfov_deg=None, mount_height=1.5, fog_length=25.0, max_range=12.0,
    fade=2.0, fog_level=0.6, blur_px=1.0, vblur_px=0.7,
)


@dataclasses.dataclass(frozen=True)
class LogSpec:
    """One benchmark log: how it is rendered and the parameters both engines read."""

    name: str
    camera: Camera
    camera_hz: float
    encoding: ImageEncoding
    params: Params
    what: str


LOGS = {
    spec.name: spec
    for spec in (
        LogSpec("matching", FORWARD_CAMERA, 5.0, "mono8", PARAMS, "160x120 mono8, 60x20 patch-normalised templates"),
        LogSpec("panoramic", GROUND_CAMERA, 1.0, "mono8", preset("circle"), "256x64 360 deg, circle preset, 80x80x35"),
        LogSpec("light", FORWARD_CAMERA, 5.0, "jpeg", LIGHT_PARAMS, "160x120 JPEG, recognised 60x20 templates"),
    )
}


def make_log(work: Path, spec: LogSpec, laps: float) -> Path:
    """Render a log once (cached in ``work``): the ``loop`` scenario seen by the spec's camera."""
    log = work / f"loop_{spec.name}_{laps:g}laps.bag"
    if log.exists():
        return log
    plan = plan_scenario("loop", 0, params={"laps": laps})
    rates = dataclasses.replace(plan.rates, camera_hz=spec.camera_hz)
    plan = dataclasses.replace(plan, camera=spec.camera, rates=rates)
    session = plan.single if plan.single is not None else plan.sessions[0]
    drive = simulate_session(plan, session, 0, 0)
    partial = work / f"{log.stem}.part.bag"
    frames = render_frames(plan, drive, 0, 0)
    written = write_log(partial, "bag", frames, drive.odometry, drive.ground_truth, image_encoding=spec.encoding)
    Path(written).rename(log)
    return log


def export_frames(log: Path, out: Path) -> int:
    """Decode every frame once into the driver's input file (cached); return the frame count."""
    with open_log(log) as opened:
        count = opened.count_frames()
        if out.exists():
            return count
        partial = out.with_suffix(".part")
        writer = FrameWriter(partial, count)
        for frame in opened.frames():
            m = frame.motion
            writer.add(frame.stamp_ns * 1e-9, m.dx, m.dyaw, m.dt, frame.image)
    writer.close()
    partial.rename(out)
    return writer.count


def time_process(log: Path, ini: Path, out: Path, checkout: Path = REPO, settings: str | None = None) -> float:
    """Wall-clock seconds of ``mapserver process`` of ``checkout`` as a fresh process (start-up included)."""
    code = "import sys; from mapserver.cli import entry; sys.argv[0] = 'mapserver'; sys.exit(entry())"
    cmd = [sys.executable, "-c", code, "process", str(log), "--config", str(ini), "--out", str(out)]
    cmd += ["--set", settings] if settings else []
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    started = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, check=False, cwd=checkout, env=env)
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        msg = f"mapserver process failed ({done.returncode}): {done.stderr[-2000:]}"
        raise HarnessError(msg)
    return seconds


def matched_share_cxx(cxx: CxxRun) -> float:
    """Share of OpenRatSLAM's frames whose template existed before the frame."""
    ids = cxx.trace["template"].astype(int)
    newest = -1
    matched = 0
    for template in ids.tolist():
        matched += int(template <= newest)
        newest = max(newest, template)
    return matched / max(ids.size, 1)


def map_facts(path: Path) -> tuple[float, str, int]:
    """Return (share of frames that matched an existing template, SHA-256 of the experience poses, templates)."""
    doc = json.loads(path.read_text())
    frames = doc.get("frames", [])
    matched = sum(1 for row in frames if int(row[2]) == 0) / max(len(frames), 1)
    keys = ("x", "y", "z", "qx", "qy", "qz", "qw", "yaw")
    poses = [[float(e[k]) for k in keys] for e in doc["experiences"]]
    digest = hashlib.sha256(json.dumps(poses).encode()).hexdigest()[:16]
    return matched, digest, int(doc["templates"])


def bench_log(spec: LogSpec, args: argparse.Namespace, binary: Path, work: Path) -> dict[str, list[float]]:
    """Time the engines ``args.runs`` times side by side on one log; print every run; return the ratios.

    Every run times OpenRatSLAM, then this checkout's ``mapserver process`` (and the baseline's, when given).
    """
    log = make_log(work, spec, args.laps)
    ini = work / f"{spec.name}.ini"
    write_ini(spec.params, ini)
    frames = export_frames(log, work / f"{spec.name}_frames.bin")
    print(f"\n== {spec.name}: {log.name}, {frames} frames, {spec.what}")
    checkouts = {"mapserver": REPO} | ({"baseline": args.baseline} if args.baseline else {})
    ratios: dict[str, list[float]] = {name: [] for name in checkouts}
    for run in range(1, args.runs + 1):
        cxx = run_driver(binary, ini, work / f"{spec.name}_frames.bin", work / f"cxx_{spec.name}")
        line = f"run {run}: OpenRatSLAM {cxx.frames_per_s:6.0f} frames/s ({frames / cxx.frames_per_s:6.2f} s)"
        for name, checkout in checkouts.items():
            out = work / f"map_{spec.name}_{name}.json"
            seconds = time_process(log, ini, out, checkout, args.set)
            ratios[name].append(frames / seconds / cxx.frames_per_s)
            matched, digest, templates = map_facts(out)
            rate = frames / seconds
            line += f" | {name} {rate:6.0f} frames/s ({seconds:6.2f} s) {ratios[name][-1]:.2f}x poses {digest}"
        print(line + f" | matched {matched:.1%} (C++ {matched_share_cxx(cxx):.1%}), {templates} templates")
    for name, values in ratios.items():
        print(f"{spec.name}: {name} / OpenRatSLAM, median of {args.runs}: {statistics.median(values):.2f}x")
    return ratios


def write_only(work: Path, names: list[str], laps: float) -> int:
    """Write each named log and its INI (``NAME.ini``) into ``work``, print their paths; return 0.

    The logs other tools measure on (``bench/robust_share.py mapserver process LOG --config INI``) without
    OpenRatSLAM's build.
    """
    work.mkdir(parents=True, exist_ok=True)
    for name in names:
        log = make_log(work, LOGS[name], laps)
        ini = work / f"{name}.ini"
        write_ini(LOGS[name].params, ini)
        print(f"{name}: {log} --config {ini}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Build the logs and the driver, time both engines on every log, print the runs and the ratios."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ratslam", type=Path, default=None, help="local copy of davidmball/ratslam")
    parser.add_argument("--write-only", type=Path, default=None, metavar="DIR",
                        help="write the logs and their INI files into DIR and stop (no C++ build, no timing)")
    parser.add_argument("--logs", default=",".join(LOGS), help=f"comma-separated, of {', '.join(LOGS)}")
    parser.add_argument("--runs", type=int, default=3, help="side-by-side runs per log")
    parser.add_argument("--laps", type=float, default=8.0)
    parser.add_argument("--work", type=Path, default=None, help="work folder (default: a temporary one)")
    parser.add_argument("--baseline", type=Path, default=None, help="another checkout to time in the same runs")
    parser.add_argument("--set", default=None, metavar="KEY=VALUE,...", help="engine parameters for mapserver alone")
    args = parser.parse_args(argv)
    names = [n.strip() for n in args.logs.split(",") if n.strip()]
    unknown = [n for n in names if n not in LOGS]
    if unknown or args.runs < 1:
        print(f"error: unknown logs {unknown} (valid: {', '.join(LOGS)}) or --runs < 1", file=sys.stderr)
        return 2
    if args.write_only is not None:
        return write_only(args.write_only, names, args.laps)
    if args.ratslam is None:
        print("error: --ratslam is required unless --write-only", file=sys.stderr)
        return 2
    work = args.work or Path(tempfile.mkdtemp(prefix="vs_openratslam_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        binary = build_driver(args.ratslam, work / "build")
        summary = {name: bench_log(LOGS[name], args, binary, work) for name in names}
    except HarnessError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print("\nratios (mapserver process end to end / OpenRatSLAM SLAM loop), run by run:")
    for log_name, by_checkout in summary.items():
        for name, ratios in by_checkout.items():
            runs = "  ".join(f"{r:.2f}x" for r in ratios)
            print(f"  {log_name:10s} {name:10s} {runs}   median {statistics.median(ratios):.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Speed against OpenRatSLAM's C++ core on one long log: ``mapserver process`` end to end vs the C++ SLAM only.

Usage (from the repository root; needs a local copy of davidmball/ratslam and Boost's headers, see
bench/differential/cxx.py)::

    PYTHONPATH=$PWD .venv/bin/python bench/vs_openratslam.py --ratslam /tmp/ratslam [--laps 8] [--work DIR]

The log is the simulator's ``loop`` scenario (``--laps`` laps, seed 0) seen by a forward camera of
160×120 pixels at 5 Hz (issue 13's long mission: 8 laps ≈ 5,500 frames). The parameters are
OpenRatSLAM's defaults with 60×20 templates on the 21×21×36 lattice (written as an INI file that both
engines read). mapserver's figure is ``mapserver process LOG --config INI`` timed as a subprocess: start-up,
bag reading, decoding, SLAM and writing the map. OpenRatSLAM's is the driver's SLAM loop alone, frames
decoded beforehand. Both run in this one invocation; the ratio (mapserver / OpenRatSLAM) is printed last.
Timings on a shared machine are noisy: compare runs made side by side.
"""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent / "differential"))

from cxx import FrameWriter, HarnessError, build_driver, run_driver, write_ini

from core import Params
from mapserver.ingest.reader import open_log
from mapserver.ingest.simulator.output import plan_scenario, render_frames, simulate_session
from mapserver.ingest.simulator.render import Camera
from mapserver.ingest.writer import write_log

PARAMS = Params().replace(
    template_x_size=60, template_y_size=20, vt_match_threshold=0.08, vt_patch_normalise=2, vt_shift_match=5,
    vt_step_match=1,
    pc_cell_x_size=0.25, exp_delta_pc_threshold=2.0, exp_loops=20, exp_initial_em_deg=0.0,
)
FORWARD_CAMERA = Camera(
    width=160, height=120, hfov_deg=90.0, vfov_deg=None, mount_height=1.5, fog_length=25.0, max_range=12.0,
    fade=2.0, fog_level=0.6, blur_px=1.0, vblur_px=0.7,
)


def make_log(work: Path, laps: float) -> Path:
    """Render the long forward-camera log once (cached in ``work``)."""
    log = work / f"loop_forward_{laps:g}laps.bag"
    if log.exists():
        return log
    plan = plan_scenario("loop", 0, params={"laps": laps})
    plan = dataclasses.replace(plan, camera=FORWARD_CAMERA, rates=dataclasses.replace(plan.rates, camera_hz=5.0))
    session = plan.single if plan.single is not None else plan.sessions[0]
    drive = simulate_session(plan, session, 0, 0)
    partial = work / f"{log.stem}.part.bag"
    written = write_log(partial, "bag", render_frames(plan, drive, 0, 0), drive.odometry, drive.ground_truth)
    Path(written).rename(log)
    return log


def export_frames(log: Path, out: Path) -> int:
    """Decode every frame once into the driver's input file; return the frame count."""
    with open_log(log) as opened:
        writer = FrameWriter(out, opened.count_frames())
        for frame in opened.frames():
            m = frame.motion
            writer.add(frame.stamp_ns * 1e-9, m.dx, m.dyaw, m.dt, frame.image)
    writer.close()
    return writer.count


def time_process(log: Path, ini: Path, out: Path) -> float:
    """Wall-clock seconds of ``mapserver process`` as a fresh process (start-up included)."""
    code = "import sys; from mapserver.cli import entry; sys.argv[0] = 'mapserver'; sys.exit(entry())"
    cmd = [sys.executable, "-c", code, "process", str(log), "--config", str(ini), "--out", str(out)]
    started = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        msg = f"mapserver process failed ({done.returncode}): {done.stderr[-2000:]}"
        raise HarnessError(msg)
    return seconds


def main(argv: list[str] | None = None) -> int:
    """Build the log and the driver, time both engines, print both figures and the ratio."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ratslam", required=True, type=Path, help="local copy of davidmball/ratslam")
    parser.add_argument("--laps", type=float, default=8.0)
    parser.add_argument("--work", type=Path, default=None, help="work folder (default: a temporary one)")
    args = parser.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="vs_openratslam_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        binary = build_driver(args.ratslam, work / "build")
    except HarnessError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    log = make_log(work, args.laps)
    ini = work / "params.ini"
    write_ini(PARAMS, ini)
    frames = export_frames(log, work / "frames.bin")
    cxx = run_driver(binary, ini, work / "frames.bin", work / "cxx")
    try:
        seconds = time_process(log, ini, work / "map.json")
    except HarnessError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    ours = frames / seconds
    print(f"log: {log.name}, {frames} frames, 160x120, 60x20 templates, 21x21x36 lattice")
    print(f"OpenRatSLAM C++ core (SLAM only, frames decoded beforehand): {cxx.frames_per_s:.0f} frames/s")
    print(f"mapserver process (start-up + read + decode + SLAM + write): {ours:.0f} frames/s ({seconds:.2f} s)")
    print(f"ratio mapserver / OpenRatSLAM: {ours / cxx.frames_per_s:.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Differential harness: mapserver's engine against OpenRatSLAM's C++ core on the same frames and odometry.

Usage (from the repository root; not part of ``make test``)::

    git clone https://github.com/davidmball/ratslam /tmp/ratslam     # once, outside this repository (GPL v3)
    apt-get install libboost-dev                                    # once: Boost headers for the C++ core
    PYTHONPATH=$PWD .venv/bin/python bench/differential/run.py --ratslam /tmp/ratslam \
        [--scenarios loop,figure8,ellipse,cave3d] [--compat] [--record tests/data/differential]

For each scenario it simulates the ``single`` session (our simulator, seed 0), decodes every frame once and
feeds the same images and per-frame odometry to both engines: ours through ``Engine.step`` and
OpenRatSLAM's through our driver (``driver.cpp``: the ROS nodes' call order, see its header). It prints
per-frame agreement (template id, experience id, action, pose-cell peak), the final experience poses'
difference, both APEs against ground truth (xy; OpenRatSLAM has no z), and both engines' SLAM frames/s.
``--compat`` runs our engine with ``openratslam_compat = true``; ``--from-ini`` runs it with the parameters
of the INI file that OpenRatSLAM reads and our defaults for everything else (what ``mapserver process LOG
--config ratslam.ini`` does: a user's OpenRatSLAM config, unchanged); ``--record DIR`` writes OpenRatSLAM's
trace and final poses as CSV (ids and numbers) for the tests. The script fetches nothing.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from cxx import CxxRun, FrameWriter, HarnessError, angle_diff, build_driver, run_driver, wrapped, write_ini

from core import Engine, Params, preset
from core.config import load_config
from mapserver.evaluation import ape_positions, interpolate_poses
from mapserver.formats import read_tum
from mapserver.ingest.reader import open_log
from mapserver.ingest.simulator import simulate as run_simulator

SCENARIOS = ("loop", "figure8", "ellipse", "cave3d")


def simulate(scenario: str, out: Path) -> dict:
    """Simulate ``scenario`` (seed 0) into ``out`` unless it is there already; return its scenario.json."""
    meta = out / "scenario.json"
    if not (out / "single.bag").exists():
        run_simulator(scenario, out, only=["single"])
    return json.loads(meta.read_text())


def run_ours(log: Path, params: Params, writer: FrameWriter | None) -> tuple[dict[str, np.ndarray], Engine, float]:
    """Run our engine over ``log`` (frames decoded first); return its trace, the engine and SLAM frames/s."""
    frames = []
    with open_log(log) as opened:
        for frame in opened.frames():
            frames.append(frame)
            if writer is not None:
                m = frame.motion
                writer.add(frame.stamp_ns * 1e-9, m.dx, m.dyaw, m.dt, frame.image)
    if writer is not None:
        writer.close()
    engine = Engine(params)
    rank = engine.pose_cells.rank
    rows = np.zeros((len(frames), 7))
    started = time.perf_counter()
    for i, frame in enumerate(frames):
        r = engine.step(frame.image, frame.motion, frame.stamp_ns * 1e-9)
        best = engine.pose_cells.best
        rows[i] = (r.template, int(r.action), r.experience, best[0], best[1], best[rank - 1], frame.stamp_ns * 1e-9)
    seconds = time.perf_counter() - started
    names = ("template", "action", "experience", "pc_x", "pc_y", "pc_th", "stamp")
    return {n: rows[:, i] for i, n in enumerate(names)}, engine, len(frames) / seconds


def ape_xy(stamps: np.ndarray, xy: np.ndarray, gt_path: Path) -> float:
    """APE RMSE (xy, rigid Umeyama alignment) of positions stamped ``stamps`` against a TUM ground truth."""
    gt = read_tum(gt_path).sorted()
    at = interpolate_poses(gt, stamps, max_diff_s=0.05)
    ok = ~np.isnan(at[:, 0])
    return float(ape_positions(at[ok][:, :2], xy[ok]).rmse)


def cxx_stamps(cxx: CxxRun, stamps: np.ndarray) -> np.ndarray:
    """Creation stamp of each OpenRatSLAM experience (the frame whose action created it)."""
    t = cxx.trace
    created = (t["action"] == 1).nonzero()[0]
    out = np.full(cxx.experiences.shape[0], np.nan)
    out[t["dest"][created].astype(int)] = stamps[created]
    return out


def compare(ours: dict[str, np.ndarray], cxx: CxxRun, engine: Engine, params: Params) -> dict[str, float]:
    """Per-frame agreement and final pose differences (poses only when both maps have the same experiences)."""
    t = cxx.trace
    n = len(ours["template"])
    same_t = ours["template"] == t["template"]
    same_e = ours["experience"] == t["experience"]
    result = {
        "frames": n,
        "template_pct": 100.0 * float(np.mean(same_t)),
        "experience_pct": 100.0 * float(np.mean(same_e)),
        "action_pct": 100.0 * float(np.mean(ours["action"] == t["action"])),
        "both_ids_pct": 100.0 * float(np.mean(same_t & same_e)),
        "first_template_diff": int(np.argmin(same_t)) if not same_t.all() else -1,
        "first_experience_diff": int(np.argmin(same_e)) if not same_e.all() else -1,
    }
    if engine.pose_cells.rank == 3:
        dims = (params.pc_dim_xy, params.pc_dim_xy, params.pc_dim_th)
        # OpenRatSLAM's x() is our lattice's y and its y() our x (the layer heading runs along its y first).
        theirs = (t["pc_y"], t["pc_x"], t["pc_th"])
        keys = ("pc_x", "pc_y", "pc_th")
        d = [np.abs(wrapped(ours[k] - c, dim)) for k, c, dim in zip(keys, theirs, dims, strict=True)]
        peak = np.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
        result["pc_peak_max_cells"] = float(peak.max())
        result["pc_peak_within_1e-6_pct"] = 100.0 * float(np.mean(peak < 1e-6))
    poses = engine.map.poses
    result["experiences_ours"] = int(poses.shape[0])
    result["experiences_cxx"] = int(cxx.experiences.shape[0])
    if poses.shape[0] == cxx.experiences.shape[0]:
        result["pose_max_m"] = float(np.max(np.hypot(*(poses[:, :2] - cxx.experiences[:, :2]).T)))
        result["heading_max_rad"] = float(np.max(np.abs(angle_diff(poses[:, 3], cxx.experiences[:, 2]))))
    return result


def record(out: Path, scenario: str, cxx: CxxRun) -> None:
    """Write OpenRatSLAM's per-frame ids and final poses as CSV test data."""
    out.mkdir(parents=True, exist_ok=True)
    t = cxx.trace
    # pose-cell peak in our axis order: OpenRatSLAM's y() is our x.
    cols = np.stack([t["frame"], t["template"], t["action"], t["experience"], t["pc_y"], t["pc_x"], t["pc_th"]], axis=1)
    fmt = ["%d", "%d", "%d", "%d", "%.12g", "%.12g", "%.12g"]
    header = "frame,template,action,experience,pc_x,pc_y,pc_th"
    np.savetxt(out / f"{scenario}_trace.csv", cols, fmt=fmt, delimiter=",", header=header, comments="")
    np.savetxt(out / f"{scenario}_poses.csv", cxx.experiences, fmt="%.12g", delimiter=",", header="x_m,y_m,th_rad",
               comments="")


def one(scenario: str, args: argparse.Namespace, binary: Path, work: Path) -> None:
    """Run both engines on one scenario's single session and print the comparison."""
    folder = work / scenario
    meta = simulate(scenario, folder)
    params = preset(meta["preset"]).replace(**dict(item.split("=", 1) for item in args.param))
    log, gt = folder / "single.bag", folder / "single.tum"
    ini = folder / "ratslam.ini"
    write_ini(params, ini)
    if args.from_ini:
        params = load_config(ini)
    if args.compat:
        params = params.replace(openratslam_compat=True)
    writer = FrameWriter(folder / "frames.bin", _count(log))
    ours, engine, ours_fps = run_ours(log, params, writer)
    cxx = run_driver(binary, ini, folder / "frames.bin", folder / "cxx")
    stats = compare(ours, cxx, engine, params)
    if not args.compat:
        engine.settle()
    poses = engine.map.poses
    stamps = np.asarray(engine.snapshot()["em_stamp"])
    ape_ours = ape_xy(stamps, poses[:, :2], gt)
    ape_cxx = ape_xy(cxx_stamps(cxx, ours["stamp"]), cxx.experiences[:, :2], gt)
    mode = ("compat" if args.compat else "default") + (", from the INI" if args.from_ini else "")
    print(f"== {scenario} ({meta['preset']}, {mode}, {stats['frames']} frames)")
    for key, value in stats.items():
        print(f"   {key}: {value:.6g}" if isinstance(value, float) else f"   {key}: {value}")
    print(f"   APE xy: mapserver {ape_ours:.3f} m   OpenRatSLAM {ape_cxx:.3f} m")
    print(f"   SLAM frames/s: mapserver {ours_fps:.0f}   OpenRatSLAM {cxx.frames_per_s:.0f}  (noisy: shared machine)")
    if args.record is not None:
        record(Path(args.record), scenario, cxx)


def _count(log: Path) -> int:
    with open_log(log) as opened:
        return opened.count_frames()


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, build the driver once and compare each scenario."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ratslam", required=True, type=Path, help="local copy of davidmball/ratslam")
    parser.add_argument("--scenarios", default=",".join(SCENARIOS))
    parser.add_argument("--work", type=Path, default=None, help="work folder (default: a temporary one)")
    parser.add_argument("--compat", action="store_true", help="our engine with openratslam_compat = true")
    parser.add_argument("--from-ini", action="store_true", help="our engine from OpenRatSLAM's INI (our defaults)")
    parser.add_argument("--param", action="append", default=[], metavar="KEY=VALUE", help="override a parameter")
    parser.add_argument("--record", default=None, help="write OpenRatSLAM's traces as CSV here")
    args = parser.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="ratslam_diff_"))
    try:
        binary = build_driver(args.ratslam, work / "build")
        for scenario in args.scenarios.split(","):
            one(scenario.strip(), args, binary, work)
    except HarnessError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

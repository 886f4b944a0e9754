"""Generalisation bench: the engine's defaults against OpenRatSLAM's behaviour on logs nobody tuned them to.

Usage (from the repository root)::

    PYTHONPATH=$PWD .venv/bin/python bench/generalisation.py [--seeds 20] [--families street,campus,dusk,park]
        [--work DIR] [--jobs 2] [--ratslam /tmp/ratslam] [--variant NAME:KEY=VALUE,KEY=VALUE ...] [--json-rows]

Each family is a kind of log a forward-camera robot records, and each seed draws its own vehicle, so no two
runs share a camera, a speed or an odometry error (:func:`draw`):

* ``street`` — laps of a city block between repeated façades (the simulator's ``street`` scenario), 7–14 m
  wide, its buildings' façades drawn from 3–24 window bays;
* ``campus`` — the ``loop`` scenario's world of free-standing walls and boxes, seen by a forward camera;
* ``dusk`` — ``street`` with the light changing between laps: the sun turns 30–90° and the exposure falls
  15–35 % per lap;
* ``park`` — the ``figure8`` world (a figure-eight: crossings seen from four directions), a moderate light
  change. **Held out**: not used to choose defaults; reported apart.

Per seed, in every family: a 160 × 120 camera with a 40–90° field of view at 5–15 Hz, JPEG quality 60–95,
wheel odometry at 10–50 Hz with a 1–5 % speed scale error and a 0.002–0.012 rad/s yaw-rate bias, a speed of
0.3–2 m/s, 1.5–2.5 laps of a route whose lap takes 50–100 s. Seeds 14 and up are held out of tuning (reported
apart as ``held-out seeds``).

Both engines read the same OpenRatSLAM INI (the ``forward`` preset's keys, :func:`ini_params`): what
``mapserver process LOG --config ratslam.ini`` runs. Per run it reports the map's APE (xy, m; rigid Umeyama
alignment of each experience's position against ground truth at its creation stamp) with:

* ``default`` — the engine as it ships (``mapserver process``: every frame, then ``Engine.settle``);
  ``default_unsettled`` is the same map before the settle (the settling table);
* ``compat`` — ``openratslam_compat = true``: OpenRatSLAM's code wherever the engine departs from it;
* ``cxx`` — OpenRatSLAM's C++ core on the same decoded frames, when ``--ratslam`` names a local copy
  (``bench/differential``);
* each ``--variant NAME:KEY=VALUE,...``: the default engine with those keys changed (the departures' sweeps).

Logs are rendered once into ``--work`` and reused. The summary gives, per family and for the held-out seeds,
the median and 90th percentile of each mode's APE ratio to ``compat``. The last line of stdout is one JSON
object: ``{"families": {family: {mode: {"median", "p90", "n"}}}, "held_out_seeds": {...}, "runs": N}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import multiprocessing
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent / "differential"))

from core import Engine, Params, preset
from mapserver.evaluation import ape_positions, interpolate_poses
from mapserver.formats import read_tum
from mapserver.ingest.reader import open_log
from mapserver.ingest.simulator.output import plan_scenario, render_frames, simulate_session, write_ground_truth
from mapserver.ingest.simulator.sensors import Sensors, fit_sensors
from mapserver.ingest.writer import write_log
from mapserver.processing.run import run_engine

HELD_OUT_FAMILY = "park"
FIRST_HELD_OUT_SEED = 14
FAMILIES = ("street", "campus", "dusk", "park")


@dataclass(frozen=True)
class Draw:
    """One seed's log: the scenario, its parameters and scale, the vehicle's sensors."""

    family: str
    seed: int
    scenario: str
    scale: float
    params: dict[str, float]
    sensors: Sensors

    @property
    def name(self) -> str:
        """Return the run's folder name."""
        return f"{self.family}-{self.seed:02d}"


def _uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def draw(family: str, seed: int, small: bool = False) -> Draw:
    """Draw one seed's vehicle and route for ``family`` (module docstring); the same arguments, the same draw.

    ``small`` (the test's): 1.2 laps at ≥ 1 m/s of the shortest routes, at most 5 frames a second — a log of a
    few hundred frames, drawn the same way otherwise.
    """
    rng = np.random.default_rng([seed, FAMILIES.index(family), 60])
    speed = _uniform(rng, 0.3, 2.0)
    light_turn, light_gain = 0.0, 0.0
    if family == "dusk":
        light_turn, light_gain = _uniform(rng, 30.0, 90.0), -_uniform(rng, 0.15, 0.35)
    elif family == "park":
        light_turn, light_gain = _uniform(rng, 10.0, 40.0), -_uniform(rng, 0.05, 0.2)
    sensors = Sensors(
        fov_deg=_uniform(rng, 40.0, 90.0), camera_hz=_uniform(rng, 5.0, 15.0), odom_hz=_uniform(rng, 10.0, 50.0),
        speed=speed, jpeg_quality=int(rng.integers(60, 96)), light_turn_deg=light_turn, light_gain=light_gain,
        scale_error=_uniform(rng, 0.01, 0.05), yaw_bias=_uniform(rng, 0.002, 0.012),
    )  # fmt: skip
    lap_m = speed * _uniform(rng, 50.0, 100.0)
    laps = _uniform(rng, 1.5, 2.5)
    if small:
        lap_m, laps = 0.0, 1.2
        sensors = dataclasses.replace(sensors, camera_hz=min(sensors.camera_hz, 5.0), speed=max(speed, 1.0))
    scenario = {"street": "street", "dusk": "street", "campus": "loop", "park": "figure8"}[family]
    params: dict[str, float] = {"laps": laps}
    if scenario == "street":  # a block of aspect 1.2-2.5 whose lap (corners of 3 m) is lap_m long, at least 8 m deep
        aspect = _uniform(rng, 1.2, 2.5)
        depth = max(8.0, (lap_m + (8.0 - 2.0 * math.pi) * 3.0) / (2.0 * (1.0 + aspect)))
        params.update(block_w_m=aspect * depth, block_h_m=depth, street_m=_uniform(rng, 7.0, 14.0),
                      palette=float(rng.integers(3, 25)))
        return Draw(family, seed, scenario, 1.0, params, sensors)
    base = plan_scenario(scenario, seed, params=params).single
    assert base is not None
    scale = float(np.clip(lap_m / base.spec.route.length, 0.4, 2.5))
    return Draw(family, seed, scenario, scale, params, sensors)


def render(d: Draw, folder: Path) -> tuple[Path, Path]:
    """Render the seed's log and ground truth into ``folder`` unless they are there; return their paths."""
    log, gt = folder / "single.bag", folder / "single.tum"
    if log.exists() and gt.exists():
        return log, gt
    folder.mkdir(parents=True, exist_ok=True)
    plan = fit_sensors(plan_scenario(d.scenario, d.seed, scale=d.scale, params=d.params), d.sensors)
    assert plan.single is not None
    drive = simulate_session(plan, plan.single, 0, d.seed)
    write_log(folder / "part.bag", "bag", render_frames(plan, drive, d.seed, 0), drive.odometry, drive.ground_truth,
              image_encoding=plan.image_encoding, jpeg_quality=plan.jpeg_quality)  # fmt: skip
    write_ground_truth(gt, drive)
    (folder / "part.bag").rename(log)
    (folder / "draw.json").write_text(json.dumps(dataclasses.asdict(d), indent=1) + "\n")
    return log, gt


def ini_params(d: Draw, ini: dict[str, Any]) -> Params:
    """Return the parameters both engines read: the ``forward`` preset's OpenRatSLAM keys and the camera's field.

    ``ini`` (``--ini``) changes keys of the INI itself, for both engines and every mode.
    """
    return preset("forward").replace(camera_fov_deg=d.sensors.fov_deg, **ini)


def ape_xy(stamps: np.ndarray, xy: np.ndarray, gt: Path) -> float:
    """APE RMSE (xy, rigid Umeyama alignment) of positions stamped ``stamps`` against a TUM ground truth."""
    at = interpolate_poses(read_tum(gt).sorted(), stamps, max_diff_s=0.05)
    ok = ~np.isnan(at[:, 0]) & ~np.isnan(xy[:, 0])
    return float(ape_positions(at[ok][:, :2], xy[ok]).rmse)


def engine_ape(engine: Engine, gt: Path) -> float:
    """APE of the engine's map as it stands."""
    return ape_xy(np.asarray(engine.snapshot()["em_stamp"]), engine.map.poses[:, :2], gt)


def run_mode(params: Params, log: Path, gt: Path) -> dict[str, float]:
    """Run ``mapserver process``'s engine path over the log; APE before and after the settle, and the time.

    Results are cached in ``results.json`` beside the log, by parameter set: delete it (or use a new ``--work``)
    after changing the engine.
    """
    cache_file = log.parent / "results.json"
    cache = json.loads(cache_file.read_text()) if cache_file.exists() else {}
    key = hashlib.sha256(json.dumps(params.to_dict(), sort_keys=True).encode()).hexdigest()[:16]
    if key in cache:
        return cache[key]
    out = _run_mode(params, log, gt)
    cache = json.loads(cache_file.read_text()) if cache_file.exists() else {}
    cache[key] = out
    cache_file.write_text(json.dumps(cache))
    return out


def _run_mode(params: Params, log: Path, gt: Path) -> dict[str, float]:
    started = time.perf_counter()
    engine = run_engine(Engine(params, origin=0), log).engine
    out: dict[str, float] = {}
    if not params.openratslam_compat:
        out["unsettled"] = engine_ape(engine, gt)
        engine.settle()
    out["ape"] = engine_ape(engine, gt)
    out["seconds"] = time.perf_counter() - started
    out["experiences"] = engine.experience_count
    out["templates"] = engine.template_count
    out["closures"] = engine.loop_closures
    return out


def run_cxx(ratslam: Path, params: Params, log: Path, gt: Path, folder: Path) -> dict[str, float]:
    """Run OpenRatSLAM's C++ core on the log's decoded frames (same INI); its APE and SLAM frames/s."""
    from cxx import FrameWriter, build_driver, run_driver, write_ini

    binary = build_driver(ratslam, folder.parent / "build")
    ini = folder / "ratslam.ini"
    write_ini(params, ini)
    stamps = []
    with open_log(log) as opened:
        writer = FrameWriter(folder / "frames.bin", opened.count_frames())
        for frame in opened.frames():
            m = frame.motion
            writer.add(frame.stamp_ns * 1e-9, m.dx, m.dyaw, m.dt, frame.image)
            stamps.append(frame.stamp_ns * 1e-9)
    writer.close()
    cxx = run_driver(binary, ini, folder / "frames.bin", folder / "cxx")
    (folder / "frames.bin").unlink()
    created = (cxx.trace["action"] == 1).nonzero()[0]
    exp_stamps = np.full(cxx.experiences.shape[0], np.nan)
    exp_stamps[cxx.trace["dest"][created].astype(int)] = np.asarray(stamps)[created]
    return {"ape": ape_xy(exp_stamps, cxx.experiences[:, :2], gt), "frames_per_s": cxx.frames_per_s,
            "experiences": int(cxx.experiences.shape[0])}  # fmt: skip


def run_one(job: tuple[Draw, Path, Path | None, dict[str, dict[str, Any]], dict[str, Any]]) -> dict[str, Any]:
    """Render (once) and run every mode on one seed's log; return its row."""
    d, work, ratslam, variants, ini = job
    folder = work / d.name
    log, gt = render(d, folder)
    base = ini_params(d, ini)
    with open_log(log) as opened:
        frames = opened.count_frames()
    row: dict[str, Any] = {"family": d.family, "seed": d.seed, "frames": frames,
                           "speed": d.sensors.speed, "fov_deg": d.sensors.fov_deg}  # fmt: skip
    default = run_mode(base, log, gt)
    row["default"] = default["ape"]
    row["default_unsettled"] = default["unsettled"]
    row["default_s"] = default["seconds"]
    row["experiences"], row["templates"], row["closures"] = (
        default["experiences"], default["templates"], default["closures"])
    compat = run_mode(base.replace(openratslam_compat=True), log, gt)
    row["compat"], row["compat_s"] = compat["ape"], compat["seconds"]
    for name, keys in variants.items():
        result = run_mode(base.replace(**keys), log, gt)
        row[name], row[f"{name}_unsettled"] = result["ape"], result.get("unsettled", result["ape"])
    if ratslam is not None:
        cxx = run_cxx(ratslam, base, log, gt, folder)
        row["cxx"], row["cxx_fps"] = cxx["ape"], cxx["frames_per_s"]
    return row


def ratio_stats(rows: list[dict[str, Any]], mode: str, reference: str = "compat") -> dict[str, float]:
    """Median and 90th percentile of ``mode`` / ``reference`` over rows."""
    ratios = np.array([r[mode] / r[reference] for r in rows if mode in r and r[reference] > 0])
    if ratios.size == 0:
        return {"n": 0}
    return {"median": round(float(np.median(ratios)), 3), "p90": round(float(np.percentile(ratios, 90)), 3),
            "n": int(ratios.size)}  # fmt: skip


def summarise(rows: list[dict[str, Any]], modes: list[str]) -> dict[str, Any]:
    """Per family (tuning seeds) and for the held-out seeds: each mode's ratio statistics to compat."""
    out: dict[str, Any] = {"families": {}, "held_out_seeds": {}}
    for family in sorted({r["family"] for r in rows}):
        tuned = [r for r in rows if r["family"] == family and r["seed"] < FIRST_HELD_OUT_SEED]
        held = [r for r in rows if r["family"] == family and r["seed"] >= FIRST_HELD_OUT_SEED]
        out["families"][family] = {m: ratio_stats(tuned, m) for m in modes}
        out["families"][family]["compat_ape_median"] = round(float(np.median([r["compat"] for r in tuned])), 3) \
            if tuned else None
        if held:
            out["held_out_seeds"][family] = {m: ratio_stats(held, m) for m in modes}
    return out


def print_table(summary: dict[str, Any], modes: list[str]) -> None:
    """Print the ratio table (median / p90 of each mode against compat) to stderr."""
    print("ratio to compat (median / p90), tuning seeds; held-out seeds in brackets", file=sys.stderr)
    print("family".ljust(10) + "".join(m.rjust(24) for m in modes), file=sys.stderr)
    for family, stats in summary["families"].items():
        held = summary["held_out_seeds"].get(family, {})
        cells = []
        for m in modes:
            s, h = stats.get(m, {}), held.get(m, {})
            cell = f"{s['median']:.2f}/{s['p90']:.2f}" if s.get("n") else "-"
            if h.get("n"):
                cell += f" [{h['median']:.2f}/{h['p90']:.2f}]"
            cells.append(cell.rjust(24))
        print(family.ljust(10) + "".join(cells), file=sys.stderr)


def parse_variants(items: list[str]) -> dict[str, dict[str, Any]]:
    """Parse ``NAME:KEY=VALUE,KEY=VALUE`` items into {name: {key: value}} (values typed as the Params field).

    A list value names its items joined by ``+`` (``openratslam_parts=translation+decode``).
    """
    fields = {f.name: f.type for f in dataclasses.fields(Params)}
    out: dict[str, dict[str, Any]] = {}
    for item in items:
        name, _, assignments = item.partition(":")
        keys: dict[str, Any] = {}
        for pair in filter(None, assignments.split(",")):
            key, _, value = pair.partition("=")
            kind = fields[key]
            keys[key] = value.lower() in ("1", "true") if kind in (bool, "bool") else (
                int(value) if kind in (int, "int") else float(value) if kind in (float, "float")
                else value.replace("+", ","))  # a list value (openratslam_parts) joins its names with +
        out[name] = keys
    return out


def main(argv: list[str] | None = None) -> int:
    """Draw, render and run every (family, seed); print the rows' summary table and the JSON line."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--families", default=",".join(FAMILIES))
    parser.add_argument("--work", type=Path, default=None, help="render cache (default: a temporary folder)")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--ratslam", type=Path, default=None, help="local copy of davidmball/ratslam")
    parser.add_argument("--variant", action="append", default=[], metavar="NAME:KEY=VALUE,...")
    parser.add_argument("--ini", default="", metavar="KEY=VALUE,...", help="change the INI both engines read")
    parser.add_argument("--json-rows", action="store_true", help="print every run's row as a JSON line")
    parser.add_argument("--small", action="store_true", help="short logs (the test's): 1.2 laps of 20-30 s")
    args = parser.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="generalisation_"))
    variants = parse_variants(args.variant)
    ini = parse_variants([f"ini:{args.ini}"])["ini"]
    families = [f.strip() for f in args.families.split(",") if f.strip()]
    jobs = [(draw(f, s, args.small), work, args.ratslam, variants, ini)
            for f in families for s in range(args.first_seed, args.first_seed + args.seeds)]  # fmt: skip
    run: Callable[..., Any] = map
    pool = None
    if args.jobs > 1:
        pool = multiprocessing.get_context("spawn").Pool(args.jobs)
        run = pool.imap
    rows = []
    for row in run(run_one, jobs):
        rows.append(row)
        if args.json_rows:
            print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}), flush=True)
    if pool is not None:
        pool.close()
    modes = ["default", "default_unsettled", *variants, *(["cxx"] if args.ratslam else [])]
    summary = summarise(rows, modes)
    print_table(summary, modes)
    print(json.dumps({**summary, "runs": len(rows)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

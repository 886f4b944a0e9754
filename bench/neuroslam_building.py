"""NeuroSLAM's acceptance bench: does a 3-D map keep a building's two look-alike storeys apart where a 2-D one does not?

Usage (from the repository root)::

    PYTHONPATH=$PWD .venv/bin/python bench/neuroslam_building.py [--seeds 10] [--first-seed 0] [--small]
        [--work DIR] [--engines neuroslam,poseidon-lvc,circle] [--set KEY=VALUE,...]

For each seed the simulator's ``building`` scenario (two storeys of one floor plan, storey 2's surfaces partly
retextured, joined by a spiral ramp) writes its ``single`` log: laps of storey 1, the ramp, laps of storey 2.
The log is processed as ``mapserver process single.bag --preset P --out map.json`` does, with three engines:

* ``neuroslam`` — NeuroSLAM's grid cells (x, y, z) and multilayer head-direction cells (yaw, height);
* ``poseidon-lvc`` — 4-DoF RatSLAM (x, y, z, yaw pose cells);
* ``circle`` — 3-DoF RatSLAM (x, y, yaw pose cells).

and evaluated as ``mapserver evaluate map.json --ground-truth single.tum --json`` does: ``ape_rmse`` and
``ape_z_rmse`` (every engine's experience map takes the odometry's height, ``circle``'s too, so all three are
aligned in 3-D), and ``flat_z_rmse``, the height error of a map with the storeys folded onto one height (the
RMSE of the ground truth's height about its mean at the experiences' stamps).

**Floor collapse.** Each experience is given its ground-truth pose at its stamp (linear interpolation, as the
evaluation aligns them). Its floor is the storey whose height is nearest; it is *on the ramp* when its true height
is more than 5 cm from both storeys' (the vehicle stays on the floor, so only the ramp is between them; the
landings at both ends of the ramp are on their storeys). A *wrong link* joins two experiences whose true heights
differ by more than half a storey, unless it is an odometry link with an end on the ramp (the drive up the ramp
itself). The issue's rule exempts every link with an end on the ramp; a loop closure from storey 2's landing to
the foot of the ramp (0.14 m up) folded one seed's storeys onto each other (docs/journal.md), so only the
ramp's own odometry links are exempt. A seed *collapses floors* for an engine when its map
holds a wrong link. Per wrong link the bench reports its kind (``loop`` closure, or the ``odometry`` link from a
closure's target to the next new experience). What makes them: ``recognised_other_floor`` counts the frames off
the ramp that re-recognised a template made on the other storey (of ``recognised_frames`` that re-recognised
any template).

``--small`` runs a smaller building (``--scale 0.75``, one lap per storey) for tests. ``--set`` adds engine
keys to the ``neuroslam`` preset (tuning runs; the reported table uses the preset as it ships). Logs are
rendered once into ``--work`` and reused. The last line of stdout is one JSON object: ``{"seeds", "small",
"engines": {engine: {"ape_rmse": {"median", "worst"}, "ape_z_rmse": {...}, "collapsed_seeds", "wrong_links":
{"median", "worst"}}}, "runs": [per seed and engine: figures and wrong links]}``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from core import preset
from mapserver.evaluation import evaluate_map, interpolate_poses
from mapserver.formats import read_map_json, read_tum
from mapserver.ingest.simulator import simulate
from mapserver.processing.run import process_log

ENGINES = ("neuroslam", "poseidon-lvc", "circle")
SMALL = {"scale": 0.75, "params": {"laps": 1.0}}
OFF_FLOOR_M = 0.05
"""An experience more than this far from both storeys' heights is on the ramp."""


@dataclass(frozen=True)
class Floors:
    """The building's storeys, from scenario.json's ``floors``."""

    z_m: tuple[float, ...]
    storey_m: float

    @classmethod
    def from_scenario(cls, doc: Mapping[str, Any]) -> Floors:
        """Read them from a ``building`` scenario.json document."""
        return cls(tuple(doc["floors"]["z_m"]), float(doc["floors"]["storey_m"]))

    def on_ramp(self, xyz: npt.NDArray[np.float64]) -> npt.NDArray[np.bool_]:
        """Whether each (N, 3) true position is on the ramp (between the storeys' heights)."""
        return np.asarray(np.min(np.abs(xyz[:, 2:3] - np.asarray(self.z_m)[None, :]), axis=1) > OFF_FLOOR_M)

    def floor(self, xyz: npt.NDArray[np.float64]) -> npt.NDArray[np.int64]:
        """The index of the storey nearest in height to each (N, 3) true position."""
        return np.asarray(np.argmin(np.abs(xyz[:, 2:3] - np.asarray(self.z_m)[None, :]), axis=1), dtype=np.int64)


def wrong_links(
    doc: Mapping[str, Any], truth_xyz: Mapping[int, Sequence[float]], floors: Floors
) -> list[dict[str, Any]]:
    """Links that join two storeys other than by driving up the ramp (module docstring), with their kinds.

    Args:
        doc: map JSON (``links`` with ``from``, ``to``, ``kind``).
        truth_xyz: each experience's true position by id (experiences without one are skipped).
        floors: the building.

    Returns:
        ``[{"from", "to", "kind", "z": [z_from, z_to]}]``.

    """
    out = []
    for link in doc["links"]:
        a, b = int(link["from"]), int(link["to"])
        if a not in truth_xyz or b not in truth_xyz:
            continue
        pair = np.asarray([truth_xyz[a], truth_xyz[b]], dtype=np.float64)
        if abs(pair[0, 2] - pair[1, 2]) <= floors.storey_m / 2:
            continue
        if str(link["kind"]) == "odometry" and floors.on_ramp(pair).any():
            continue
        out.append(
            {
                "from": a,
                "to": b,
                "kind": str(link["kind"]),
                "z": [round(float(pair[0, 2]), 3), round(float(pair[1, 2]), 3)],
            }
        )
    return out


def cross_floor_views(doc: Mapping[str, Any], gt_path: Path, floors: Floors) -> dict[str, int]:
    """Frames off the ramp whose template was made on the other storey: the views the storeys share.

    ``frames`` of the map JSON give each frame's template; a template is made by the first frame that has it.
    """
    frames = doc.get("frames") or []
    if not frames:
        return {"frames": 0, "other_floor": 0}
    stamps = np.asarray([float(f[0]) for f in frames])
    templates = [int(f[1]) for f in frames]
    at = interpolate_poses(read_tum(gt_path).sorted(), stamps, max_diff_s=0.05)[:, :3]
    known = ~np.isnan(at[:, 0])
    level = floors.floor(np.nan_to_num(at))
    usable = known & ~floors.on_ramp(np.nan_to_num(at))
    made: dict[int, int] = {}
    other = counted = 0
    for k, t in enumerate(templates):
        if t not in made:
            made[t] = k
            continue
        if usable[k] and usable[made[t]]:
            counted += 1
            other += int(level[k] != level[made[t]])
    return {"frames": counted, "other_floor": other}


def truth_by_experience(doc: Mapping[str, Any], gt_path: Path) -> dict[int, list[float]]:
    """Each experience's true position at its stamp (ground truth interpolated as the evaluation does)."""
    exps = list(doc["experiences"])
    stamps = np.asarray([float(e["stamp"]) for e in exps])
    at = interpolate_poses(read_tum(gt_path).sorted(), stamps, max_diff_s=0.05)
    return {int(e["id"]): at[k, :3].tolist() for k, e in enumerate(exps) if not np.isnan(at[k, 0])}


def render(seed: int, work: Path, small: bool) -> Path:
    """Simulate the seed's ``building`` single log into ``work`` (once); return its folder."""
    folder = work / f"{'small' if small else 'full'}-{seed}"
    if not (folder / "scenario.json").exists():
        opts: dict[str, Any] = SMALL if small else {"scale": 1.0, "params": {}}
        simulate("building", folder, seed=seed, scale=opts["scale"], params=opts["params"], only=["single"])
    return folder


def run_engine_on(folder: Path, engine: str, overrides: Mapping[str, Any]) -> dict[str, Any]:
    """Process the folder's single log with one preset, evaluate it and find its wrong links."""
    params = preset(engine)
    if engine == "neuroslam" and overrides:
        params = params.replace(**overrides)
    started = time.perf_counter()
    out = folder / f"{engine}.json"
    result = process_log(folder / "single.bag", params, out=out).summary()
    seconds = time.perf_counter() - started
    doc = read_map_json(out)
    gt_path = folder / "single.tum"
    ev = evaluate_map(doc, read_tum(gt_path))
    truth = truth_by_experience(doc, gt_path)
    floors = Floors.from_scenario(json.loads((folder / "scenario.json").read_text()))
    wrong = wrong_links(doc, truth, floors)
    views = cross_floor_views(doc, gt_path, floors)
    true_z = np.asarray([truth[int(e["id"])][2] for e in doc["experiences"] if int(e["id"]) in truth])
    return {
        "engine": engine, "ape_rmse": ev["ape_rmse"], "ape_z_rmse": ev["ape_z_rmse"], "dims": ev["dims"],
        "flat_z_rmse": float(np.sqrt(np.mean((true_z - true_z.mean()) ** 2))),
        "odometry_ape_rmse": ev["odometry_ape_rmse"], "experiences": result["experiences"],
        "templates": result["templates"], "loop_closures": result["loop_closures"], "seconds": round(seconds, 2),
        "collapsed": bool(wrong), "wrong_links": len(wrong), "wrong": wrong[:20],
        "wrong_kinds": sorted({w["kind"] for w in wrong}),
        "recognised_frames": views["frames"], "recognised_other_floor": views["other_floor"],
    }  # fmt: skip


def _stats(values: Sequence[float | None]) -> dict[str, float | None]:
    """Median and worst (largest) of the values that are known."""
    finite = [float(v) for v in values if v is not None]
    if not finite:
        return {"median": None, "worst": None}
    return {"median": round(float(np.median(finite)), 4), "worst": round(max(finite), 4)}


def summarise(runs: list[dict[str, Any]], engines: Sequence[str]) -> dict[str, Any]:
    """Median and worst of each engine's figures over the seeds, and its count of collapsed seeds."""
    out = {}
    for engine in engines:
        rows = [r for r in runs if r["engine"] == engine]
        out[engine] = {
            "ape_rmse": _stats([r["ape_rmse"] for r in rows]),
            "ape_z_rmse": _stats([r["ape_z_rmse"] for r in rows]),
            "flat_z_rmse": _stats([r["flat_z_rmse"] for r in rows]),
            "wrong_links": _stats([r["wrong_links"] for r in rows]),
            "collapsed_seeds": sum(1 for r in rows if r["collapsed"]),
            "recognised_other_floor": _stats([r["recognised_other_floor"] for r in rows]),
            "seeds": len(rows),
        }
    return out


def _parse_set(items: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        for pair in item.split(","):
            key, _, value = pair.partition("=")
            number = float(value)
            out[key.strip()] = int(number) if number == int(number) and "." not in value else number
    return out


def main(argv: list[str] | None = None) -> int:
    """Run the bench; print one line per run (stderr) and the JSON summary (stdout)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--small", action="store_true", help="a small building (for tests)")
    parser.add_argument("--work", type=Path, default=None, help="folder for the logs (default: a temporary one)")
    parser.add_argument("--engines", default=",".join(ENGINES))
    parser.add_argument("--set", action="append", default=[], help="neuroslam keys KEY=VALUE,... (tuning only)")
    args = parser.parse_args(argv)
    engines = [e for e in args.engines.split(",") if e]
    overrides = _parse_set(args.set)
    with tempfile.TemporaryDirectory() as temp:
        work = args.work or Path(temp)
        runs = []
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            folder = render(seed, work, args.small)
            for engine in engines:
                row = {"seed": seed, **run_engine_on(folder, engine, overrides)}
                runs.append(row)
                print(f"seed {seed} {engine}: APE {row['ape_rmse']:.3f} m, z {row['ape_z_rmse']}, wrong links "
                      f"{row['wrong_links']} {row['wrong_kinds']}, closures {row['loop_closures']}, "
                      f"{row['seconds']} s", file=sys.stderr)  # fmt: skip
    summary = {"seeds": [args.first_seed, args.first_seed + args.seeds - 1], "small": args.small,
               "overrides": overrides, "engines": summarise(runs, engines), "runs": runs}  # fmt: skip
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Measuring robust relaxation on simulated maps (shared by tests/mapserver/test_robust_acceptance.py and
bench/robust_relaxation.py): simulate, process, inject wrong loop links (the test hook), settle, APE."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core import Engine, LinkKind, Params, params_from_dict, preset
from core.robust import false_loop_links
from mapserver.cli import main
from mapserver.evaluation import ape_positions, interpolate_poses
from mapserver.formats import Trajectory, read_tum
from mapserver.merge import online as online_module
from mapserver.params import with_settings
from mapserver.processing.pipeline import process_log
from mapserver.store import list_maps, load_map, open_database
from tests.simulations import simulate_once


@dataclass(frozen=True)
class Simulated:
    """A settled single-session map of a simulated scenario and its ground truth."""

    params: Params
    state: dict[str, np.ndarray]
    truth: Trajectory


@dataclass(frozen=True)
class Injected:
    """The map after ``k`` wrong loop links were injected and the map settled."""

    engine: Engine
    injected: np.ndarray  # link indices of the wrong links
    true_loops: int  # loop links of the clean map
    true_loops_on: int  # of those, still active


def simulate_single(
    out: Path, scenario: str, seed: int = 0, settings: str | None = None, preset_name: str | None = None
) -> Simulated:
    """Simulate ``scenario`` into ``out`` and process its single-session log with the scenario's preset.

    ``settings``: engine parameters on top of the preset (``process --set``'s syntax, e.g. ``exp_relax_joint=1``);
    ``preset_name``: another preset.
    """
    info = simulate_once(scenario, out, seed=seed, only=("single",))
    params = with_settings(preset(preset_name or info["preset"]), settings)
    result = process_log(out / info["single"]["log"], params)
    return Simulated(params, result.engine.snapshot(), read_tum(out / info["single"]["ground_truth"]))


def simulate_merged(
    out: Path,
    scenario: str,
    seed: int = 0,
    preset_name: str | None = None,
    *,
    tie_hits: bool = False,
    view_heading: bool = False,
) -> Simulated:
    """Simulate ``scenario`` into ``out``, process sessions 1 and 2 into one database with ``mapserver process --db``
    (session 2 merges into session 1's map) and return the map holding most sessions with both sessions' ground truth.

    ``preset_name``: the engine preset (default: the scenario's). ``tie_hits``: the merge ties the session's copy of
    the stored ground by its hits (``mapserver.merge.online.TIE_HITS``, on in the product). Off by
    default: the robust check's cases were found on merged maps made before the ties, and are kept on those maps
    (with the ties a merged map holds more merge links, and several of the cases no longer arise there).
    ``view_heading``: ``merge_view_heading`` (on in the product); off by default for the same reason
    (the merged ``twin-overlap`` seed 3 map's closures move, and three of its cases no longer arise).
    """
    info = simulate_once(scenario, out, seed=seed, only=("session1", "session2"))
    db = f"sqlite:///{out / 'db.sqlite'}"
    product = online_module.TIE_HITS
    online_module.TIE_HITS = tie_hits
    try:
        for session in info["sessions"][:2]:
            argv = ["process", str(out / session["log"]), "--db", db, "--preset", preset_name or info["preset"]]
            argv += [] if view_heading else ["--set", "merge_view_heading=0"]
            assert main(argv) == 0
    finally:
        online_module.TIE_HITS = product
    truth = out / "both.tum"
    truth.write_text("".join((out / s["ground_truth"]).read_text(encoding="utf-8") for s in info["sessions"][:2]))
    with open_database(db) as handle:
        with handle.read() as conn:
            name = max(list_maps(conn=conn), key=lambda m: m.sessions).name
        content = load_map(handle, name=name)
    return Simulated(params_from_dict(content.params), content.snapshot, read_tum(truth))


def inject(sim: Simulated, count: int, separation: float, seed: int, robust: bool = True) -> Injected:
    """Add ``count`` wrong loop links (:func:`core.robust.false_loop_links`) to the stored map; settle it."""
    params = sim.params if robust else sim.params.replace(exp_robust=False)
    engine = Engine.restore(params, sim.state)
    first = engine.map.link_count
    src, dst, transform = false_loop_links(engine.map.poses, count, separation, seed)
    for a, b, t in zip(src.tolist(), dst.tolist(), transform, strict=True):
        engine.map.add_link_raw(a, b, t, 1.0, float(np.linalg.norm(t[:3])), LinkKind.LOOP)
    engine.settle()
    loops = np.flatnonzero(np.asarray(sim.state["em_link_kind"]) == int(LinkKind.LOOP))
    on = int(np.count_nonzero(engine.map.link_active[loops]))
    return Injected(engine, np.arange(first, engine.map.link_count), int(loops.size), on)


def world_separation(sim: Simulated, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Return how far apart (m) in the world the experiences ``src`` and ``dst`` of the map ``sim`` were created.

    A true loop closure joins two experiences whose views matched, which RatSLAM does within a metre or two: the
    separation of a map's own closures is the scale below which a wrong link is as plausible as they are.
    """
    ref = interpolate_poses(sim.truth, sim.state["em_stamp"], max_diff_s=0.1)
    dims = _dims(sim.state["em_pose"])
    return np.linalg.norm(ref[np.asarray(src), :dims] - ref[np.asarray(dst), :dims], axis=1)


def closure_separation(sim: Simulated) -> np.ndarray:
    """Return the world separation (m) of the loop and merge links switched on in ``sim`` (:func:`world_separation`)."""
    closure = np.isin(np.asarray(sim.state["em_link_kind"]), (int(LinkKind.LOOP), int(LinkKind.MERGE)))
    closure &= np.asarray(sim.state["em_link_active"], dtype=bool)  # the map's switched-off links are not its closures
    apart = world_separation(sim, sim.state["em_link_from"][closure], sim.state["em_link_to"][closure])
    return apart[np.isfinite(apart)]  # an end outside the ground truth's time span has no place to compare


def closure_range(closures: np.ndarray) -> str:
    """Return the range of the closures' world separations (:func:`closure_separation`) as text, e.g. "0.18-1.86 m"."""
    return f"{closures.min() if closures.size else 0.0:.2f}-{closures.max(initial=0.0):.2f} m"


def separation_figures(apart: np.ndarray, closures: np.ndarray) -> tuple[float, float]:
    """Return the wrong links' world separation ``apart`` (m) as its median and the share no farther apart than the
    farthest of the map's own ``closures`` (:func:`closure_separation`): (0, 0) when none has a place to compare."""
    apart = apart[np.isfinite(apart)]
    if not apart.size:
        return 0.0, 0.0
    return float(np.median(apart)), float(np.mean(apart <= closures.max(initial=0.0)))


def map_ape(pose: np.ndarray, stamps: np.ndarray, truth: Trajectory) -> float:
    """Return the APE RMSE of experience positions after one rigid alignment (planar maps in xy)."""
    ref = interpolate_poses(truth, stamps, max_diff_s=0.1)
    keep = np.isfinite(ref).all(axis=1)
    dims = _dims(pose)
    return ape_positions(ref[keep, :dims], pose[keep, :dims]).rmse


def _dims(pose: np.ndarray) -> int:
    """Return the dimensions a map's positions are compared in: 2 for a planar map (every z zero), else 3."""
    return 2 if not np.any(pose[:, 2]) else 3

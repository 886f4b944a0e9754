"""The engine with ``openratslam_compat`` reproduces OpenRatSLAM's C++ core frame by frame.

The references in tests/data/openratslam were recorded from OpenRatSLAM's own code by the differential
harness (bench/differential; see the README there): per-frame template and experience ids, actions and
pose-cell peaks, and the final experience poses after its relaxation. Issue 13 asks for ≥ 99 % of frames
with identical ids and final poses within 1 mm; the default engine, which departs on purpose, is checked
to differ (the anchored, settled map is not OpenRatSLAM's).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core import Engine, preset
from core.angles import wrap_angle
from mapserver.ingest.reader import open_log
from tests.simulations import simulate_once

DATA = Path(__file__).resolve().parents[1] / "data" / "openratslam"
# as recorded (README there): the scenario's preset with exp_loops=10; cave3d on a 3-DoF lattice, gates off
PARAMS = {
    "loop": preset("circle").replace(exp_loops=10),
    "figure8": preset("circle").replace(exp_loops=10),
    "ellipse": preset("circle").replace(exp_loops=10),
    "cave3d": preset("poseidon-lvc").replace(exp_loops=10, pc_dim_z=1, vpr_guard=False, motion_gate=False),
}

pytestmark = pytest.mark.slow


def _reference(scenario: str) -> tuple[np.ndarray, np.ndarray]:
    trace = np.loadtxt(DATA / f"{scenario}_trace.csv", delimiter=",", skiprows=1)
    poses = np.loadtxt(DATA / f"{scenario}_poses.csv", delimiter=",", skiprows=1, ndmin=2)
    return trace, poses


def _run(scenario: str, folder: Path, compat: bool) -> tuple[np.ndarray, Engine]:
    simulate_once(scenario, folder, only=["single"])
    engine = Engine(PARAMS[scenario].replace(openratslam_compat=compat))
    rows = []
    with open_log(folder / "single.bag") as log:
        for frame in log.frames():
            r = engine.step(frame.image, frame.motion, frame.stamp_ns * 1e-9)
            rows.append((r.template, int(r.action), r.experience, *engine.pose_cells.best))
    if not compat:
        engine.settle()
    return np.array(rows, dtype=np.float64), engine


def _wrapped(delta: np.ndarray, period: float) -> np.ndarray:
    return (delta + period / 2.0) % period - period / 2.0


@pytest.mark.parametrize("scenario", ["loop", "figure8", "ellipse", "cave3d"])
def test_compat_engine_matches_openratslam_trace(scenario: str, tmp_path: Path) -> None:
    ref, ref_poses = _reference(scenario)
    ours, engine = _run(scenario, tmp_path, compat=True)
    assert ours.shape[0] == ref.shape[0]
    same_ids = (ours[:, 0] == ref[:, 1]) & (ours[:, 2] == ref[:, 3])
    assert same_ids.mean() >= 0.99
    assert (ours[:, 1] == ref[:, 2]).mean() >= 0.99
    p = PARAMS[scenario]
    dims = np.array([p.pc_dim_xy, p.pc_dim_xy, p.pc_dim_th], dtype=np.float64)
    peak = np.linalg.norm(_wrapped(ours[:, 3:6] - ref[:, 4:7], dims), axis=1)
    assert (peak < 1e-6).mean() >= 0.99
    poses = engine.map.poses
    assert poses.shape[0] == ref_poses.shape[0]
    assert np.hypot(*(poses[:, :2] - ref_poses[:, :2]).T).max() < 1e-3
    assert np.abs(wrap_angle(poses[:, 3] - ref_poses[:, 2])).max() < 1e-6


def test_default_engine_makes_the_same_decisions_but_not_openratslams_map(tmp_path: Path) -> None:
    ref, ref_poses = _reference("loop")
    ours, engine = _run("loop", tmp_path, compat=False)
    # the departures leave every decision of this log alone ...
    np.testing.assert_array_equal(ours[:, [0, 2]], ref[:, [1, 3]])
    # ... but the map is relaxed to its anchored fixed point, not by OpenRatSLAM's 10 sweeps per action
    poses = engine.map.poses
    assert poses.shape[0] == ref_poses.shape[0]
    assert np.hypot(*(poses[:, :2] - ref_poses[:, :2]).T).max() > 0.1

"""Scenarios: their plans, the files simulate() writes, determinism, atomicity and the look-alike stretch."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from core import preset
from core.angles import wrap_angle_exact
from core.localview import LocalViewCells
from mapserver.errors import InputError
from mapserver.formats import read_tum
from mapserver.ingest import open_log
from mapserver.ingest.simulator import SCENARIOS, plan_scenario, render_frames, simulate, simulate_session
from mapserver.ingest.simulator import output as sim_output

EXPECTED = {
    "loop": ("circle", ["single"], True),
    "figure8": ("circle", ["single"], True),
    "ellipse": ("circle", ["session1", "session2"], True),
    "bridge": ("circle", ["session1", "session2", "session3"], False),
    "chain5": ("circle", ["session1", "session2", "session3", "session4", "session5"], False),
    "cave3d": ("poseidon", ["session1", "session2"], True),
    "aliased": ("circle", ["session1", "session2"], False),
    "twin": ("circle", ["session1", "session2"], False),
    "twin-overlap": ("circle", ["session1", "session2"], True),
    "symmetric": ("circle", ["session1", "session2"], True),
    "symmetric-overlap": ("circle", ["session1", "session2"], True),
    "street": ("forward", ["single"], True),
    "building": ("neuroslam", ["single", "floor1", "floor2", "stairs"], True),
    "terrain": ("neuroslam", ["single"], True),
    "seabed": ("poseidon-lvc", ["session1", "session2"], True),
}


def test_every_scenario_plans_with_clear_routes() -> None:
    assert set(SCENARIOS) == set(EXPECTED)
    for name, (preset_name, sessions, has_single) in EXPECTED.items():
        plan = plan_scenario(name, seed=5)
        assert plan.preset == preset_name
        assert [s.name for s in plan.sessions] == sessions
        assert (plan.single is not None) == has_single
        # no surface blocks any driven route (corridors at least 1.5 m wide each side, 0.5 m in the cave, the
        # building's stairwell 1.3 m)
        plans = [*plan.sessions, *([plan.single] if plan.single else [])]
        pts = np.vstack([s.spec.route.points(0.1) for s in plans])
        walls = np.vstack([np.linspace(a, b, 20) for a, b in zip(plan.world.p0, plan.world.p1, strict=True)])
        nearest, _ = cKDTree(walls).query(pts)
        assert nearest.min() > {"cave3d": 0.5, "seabed": 0.5, "building": 1.25}.get(name, 1.45), name


def test_ellipse_split_is_the_virtual_tour() -> None:
    plan = plan_scenario("ellipse")
    s1, s2 = plan.sessions
    length = s1.spec.route.length
    assert s1.spec.distance_m / length == pytest.approx(0.75)
    assert s2.spec.start_m / length == pytest.approx(0.875)  # in the quarter session 1 never mapped
    assert s2.spec.distance_m / length == pytest.approx(3.0)
    assert plan.single is not None and plan.single.spec.distance_m / length == pytest.approx(2.5)
    turned = plan_scenario("ellipse", params={"heading_offset_deg": 90.0}).sessions[1]
    assert turned.spec.turn_deg == 90.0 and plan.sessions[1].spec.turn_deg == 0.0


def test_bad_scenario_parameters_are_input_errors() -> None:
    with pytest.raises(InputError, match=r"unknown scenario 'moon'.*loop"):
        plan_scenario("moon")
    with pytest.raises(InputError, match=r"unknown parameter 'lapz'.*laps"):
        plan_scenario("loop", params={"lapz": 1})
    with pytest.raises(InputError, match="scale"):
        plan_scenario("loop", scale=0.0)
    with pytest.raises(InputError, match="format"):
        simulate("loop", "/nonexistent/never", fmt="zip")  # type: ignore[arg-type]


def _small(tmp_path: Path, name: str, seed: int, fmt: str = "bag") -> tuple[Path, dict]:
    out = tmp_path / name
    return out, simulate("loop", out, seed=seed, fmt=fmt, scale=0.3, params={"laps": 0.5})  # type: ignore[arg-type]


def test_simulate_writes_the_contract_files(tmp_path: Path) -> None:
    out, doc = _small(tmp_path, "loop", 3, "mcap")
    assert json.loads((out / "scenario.json").read_text()) == json.loads(json.dumps(doc))
    assert {"scenario", "preset", "sessions", "single"} <= set(doc)
    assert doc["scenario"] == "loop" and doc["preset"] == "circle"
    entry = doc["sessions"][0]
    assert entry["name"] == "single" and entry["log"] == "single.mcap" and entry["ground_truth"] == "single.tum"
    assert doc["single"]["log"] == "single.mcap"
    assert sorted(p.name for p in out.iterdir()) == ["scenario.json", "single.mcap", "single.tum"]
    gt = read_tum(out / "single.tum")
    with open_log(out / "single.mcap") as log:
        assert log.mapping.as_dict() == {
            "image": "/robot/camera/image", "odometry": "/robot/odom", "ground_truth": "/robot/ground_truth",
        }
        assert log.odometry_mode == "twist"
        frames = list(log.frames())
        truth = list(log.ground_truth())
    assert len(frames) == entry["frames"] and frames[0].image.shape == (64, 256)
    assert len(truth) == len(gt) and truth[5].x == pytest.approx(gt.positions_xyz[5, 0])


def test_same_seed_same_logs_other_seed_other_world(tmp_path: Path) -> None:
    def frames(out: Path) -> list[tuple[int, bytes]]:
        with open_log(out / "single.bag") as log:
            return [(f.stamp_ns, f.image.tobytes()) for f in log.frames()]

    a, doc_a = _small(tmp_path, "a", 7)
    b, doc_b = _small(tmp_path, "b", 7)
    c, _ = _small(tmp_path, "c", 8)
    assert doc_a == doc_b
    assert frames(a) == frames(b)
    assert (a / "single.tum").read_text() == (b / "single.tum").read_text()
    assert [f[1] for f in frames(a)] != [f[1] for f in frames(c)]


def test_failure_leaves_nothing_half_written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def boom(*_a: object, **_k: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(sim_output, "write_tum", boom)
    fresh = tmp_path / "fresh"
    with pytest.raises(OSError, match="disk full"):
        simulate("loop", fresh, scale=0.3, params={"laps": 0.3})
    assert not fresh.exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "scenario.json").write_text("old")
    with pytest.raises(OSError, match="disk full"):
        simulate("loop", kept, scale=0.3, params={"laps": 0.3})
    assert [p.name for p in kept.iterdir()] == ["scenario.json"]
    assert (kept / "scenario.json").read_text() == "old"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary left


def _templates(plan: object, index: int, seed: int) -> tuple[np.ndarray, list[tuple[np.ndarray, float]]]:
    lv = LocalViewCells(preset("circle"))
    drive = simulate_session(plan, plan.sessions[index], index, seed)  # type: ignore[attr-defined]
    views = [lv.make_template(image) for _, image in render_frames(plan, drive, seed, index)]  # type: ignore[arg-type]
    return drive.frame_poses, views


@pytest.mark.slow
def test_aliased_places_match_for_one_or_two_consecutive_frames_only_on_the_stretch() -> None:
    """Session 2's frames against session 1's templates (built as the engine builds them, circle preset)."""
    seed = 0
    plan = plan_scenario("aliased", seed)
    threshold = preset("circle").vt_match_threshold
    _, views_a = _templates(plan, 0, seed)
    poses_b, views_b = _templates(plan, 1, seed)
    store = LocalViewCells(preset("circle"))
    for template, mean in views_a:
        best, error, _ = store.match(template, mean)
        if best < 0 or error > threshold:
            store.add_templates(template[None], np.array([mean]))
    matched = [k for k, (t, m) in enumerate(views_b) if store.match(t, m)[1] <= threshold]
    assert 1 <= len(matched) <= 2
    assert matched == list(range(matched[0], matched[0] + len(matched)))  # consecutive
    centre_b = np.asarray(plan.info["alias"]["centres"][1])
    for k in matched:  # on (or within a frame of) the look-alike stretch, heading east
        assert np.linalg.norm(poses_b[k, :2] - centre_b) < 0.8
        assert abs(wrap_angle_exact(poses_b[k, 3])) < math.radians(20)

"""The look-alike scenarios (issue 12): twin places sharing a stretch, a point-symmetric loop, and their overlaps.

Views are compared noise-free (:func:`render` at route poses) by their mean absolute radiance difference:
two renderings of the same scene from the same relative pose agree to rounding (< 1e-3), views of a
look-alike structure agree to < 0.01 (near its ends a few far columns see past it), different scenes
differ by 0.05 or more (textures are in [0.02, 0.98], fog 0.6).
"""

from __future__ import annotations

import functools
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
from mapserver.ingest.simulator import plan_scenario, render, render_frames, simulate, simulate_session
from mapserver.ingest.simulator.lookalike import symmetric_sectors
from mapserver.ingest.simulator.scenarios import Plan

SAME = 1e-3
ALIKE = 0.01
DIFFERENT = 0.05
STEP = 0.25


@functools.cache
def _plan(name: str, seed: int, **params: float) -> Plan:
    """plan_scenario, cached: building the twin world takes about a second."""
    return plan_scenario(name, seed, params=params)


def _view(plan: Plan, x: float, y: float, yaw: float) -> np.ndarray:
    return render(plan.world, plan.camera, float(x), float(y), 0.0, float(yaw))


def _stretch_differences(plan: Plan, stretch: float, offsets: np.ndarray) -> np.ndarray:
    """Mean |difference| of the two sessions' route views at the same arc offset from their stretch's start."""
    route_1, route_2 = (s.spec.route for s in plan.sessions)  # both start at the middle of their stretch
    out = []
    for u in offsets:
        s = -stretch / 2 + float(u)
        p1, p2 = route_1.position(s), route_2.position(s)
        v1 = _view(plan, p1[0], p1[1], route_1.heading(s))
        v2 = _view(plan, p2[0], p2[1], route_2.heading(s))
        out.append(float(np.abs(v1 - v2).mean()))
    return np.array(out)


@pytest.mark.parametrize("stretch", [5.0, 12.0])
def test_twin_places_look_the_same_exactly_along_the_stretch(stretch: float) -> None:
    plan = _plan("twin", 1, lookalike_m=stretch)
    offsets = np.arange(-4.0, stretch + 4.0 + 1e-9, STEP)
    diff = _stretch_differences(plan, stretch, offsets)
    same = offsets[diff < ALIKE]
    # the identical views cover the stretch (the parameter) and nothing else, to a sample
    assert same.min() == pytest.approx(0.0, abs=0.3) and same.max() == pytest.approx(stretch, abs=0.3)
    assert (len(same) - 1) * STEP == pytest.approx(stretch, abs=0.3)
    assert np.all(np.diff(np.flatnonzero(diff < ALIKE)) == 1)  # one run
    outside = (offsets < -1.5) | (offsets > stretch + 1.5)
    assert diff[outside].min() > DIFFERENT


def test_twin_with_turns_alike_looks_the_same_through_both_turns() -> None:
    """``lookalike_turns = 1``: both places turn onto and off the stretch the same way, so the identical views
    reach into the legs; the route's heading changes by ≥ 90° over them (the decision's turn rule needs 45°)."""
    stretch = 5.0
    plan = _plan("twin", 1, lookalike_m=stretch, lookalike_turns=1.0)
    offsets = np.arange(-6.0, stretch + 6.0 + 1e-9, STEP)
    diff = _stretch_differences(plan, stretch, offsets)
    same = offsets[diff < ALIKE]
    assert same.min() < -2.0 and same.max() > stretch + 2.0  # well beyond the straight stretch (±1.5 m above)
    route = plan.sessions[0].spec.route
    headings = np.unwrap([route.heading(-stretch / 2 + float(u)) for u in same])
    assert headings.max() - headings.min() >= math.radians(90)
    with pytest.raises(InputError, match="lookalike_turns"):
        plan_scenario("twin", params={"lookalike_turns": 0.5})


def test_twin_places_differ_away_from_the_stretch_and_never_overlap() -> None:
    plan = _plan("twin", 2, lookalike_m=10.0)
    drives = [simulate_session(plan, s, i, 2) for i, s in enumerate(plan.sessions)]
    xy_1, xy_2 = (np.array([[g.x, g.y] for g in d.ground_truth]) for d in drives)
    # ground truth: the two places lie apart by more than twice the camera's range
    nearest, _ = cKDTree(xy_1).query(xy_2)
    assert nearest.min() > 2 * plan.camera.max_range
    # session 2's views outside its look-alike structure match none of session 1's (same heading sector)
    centre_2 = np.asarray(plan.info["lookalike"]["centres"][1])
    poses_1 = drives[0].frame_poses[::2]
    views_1 = np.stack([_view(plan, p[0], p[1], p[3]) for p in poses_1])
    far = [p for p in drives[1].frame_poses[::6] if np.linalg.norm(p[:2] - centre_2) > 15.0]
    assert len(far) > 10
    for p in far:
        view = _view(plan, p[0], p[1], p[3])
        assert np.abs(views_1 - view).mean(axis=(1, 2)).min() > DIFFERENT


def test_twin_overlap_drives_session_1_ground_and_shares_its_world() -> None:
    twin = _plan("twin", 4)
    overlap = _plan("twin-overlap", 4)
    assert np.array_equal(twin.world.p0, overlap.world.p0)
    assert np.array_equal(twin.world.tex_flat, overlap.world.tex_flat)
    a, b = twin.sessions[0].spec, overlap.sessions[0].spec
    assert np.array_equal(a.route.xy, b.route.xy) and (a.start_m, a.distance_m) == (b.start_m, b.distance_m)
    assert twin.single is None and overlap.single is not None
    d1, d2 = (simulate_session(overlap, s, i, 4) for i, s in enumerate(overlap.sessions))
    xy_1, xy_2 = (np.array([[g.x, g.y] for g in d.ground_truth]) for d in (d1, d2))
    nearest, _ = cKDTree(xy_1).query(xy_2)
    shared = nearest < 1.0
    assert shared.mean() > 0.3  # session 2 drives session 1's ground...
    # ...reaching it first at the look-alike stretch (session 1 starts lead_m before its stretch)
    first = xy_2[np.argmax(shared)]
    centre_1 = np.asarray(overlap.info["lookalike"]["centres"][0])
    assert np.linalg.norm(first - centre_1) < overlap.params["lookalike_m"] / 2 + 3.0


def test_symmetric_sectors_split_the_plane_at_180_degrees() -> None:
    angles = np.radians(np.arange(0.0, 360.0, 7.5))
    points = np.stack([np.cos(angles), np.sin(angles)], axis=1) * 5.0 + [1.0, 2.0]
    source, mirror = symmetric_sectors(points, (1.0, 2.0), math.radians(30.0), math.pi)
    assert np.all(source ^ mirror)
    narrow, opposite = symmetric_sectors(points, (1.0, 2.0), math.radians(30.0), math.radians(90.0))
    deg = np.degrees(angles)
    assert np.array_equal(narrow, (deg >= -15.0 + 0) & (deg < 75.0) | (deg >= 345.0))
    assert np.array_equal(opposite, (deg >= 165.0) & (deg < 255.0))


def _rotated_difference(plan: Plan, s: float) -> float:
    route = plan.sessions[0].spec.route
    p, th = route.position(s), float(route.heading(s))
    return float(np.abs(_view(plan, p[0], p[1], th) - _view(plan, -p[0], -p[1], th + math.pi)).mean())


def test_symmetric_world_looks_the_same_from_the_half_turned_pose() -> None:
    full = _plan("symmetric", 3, symmetric_deg=180.0)
    route = full.sessions[0].spec.route
    samples = np.linspace(0.0, route.length, 13)[:-1]
    assert max(_rotated_difference(full, s) for s in samples) < SAME
    # default 90° sectors: the NE corner looks like the SW corner, the bottom side is its own
    default = _plan("symmetric", 3)
    corner = float(route.s[np.argmax(route.xy[:, 0] + route.xy[:, 1])])
    assert _rotated_difference(default, corner) < 0.01
    assert _rotated_difference(default, 0.0) > DIFFERENT
    # no symmetric sector: the corners differ too
    assert _rotated_difference(_plan("symmetric", 3, symmetric_deg=0.0), corner) > DIFFERENT


def test_symmetric_session_2_meets_the_mirror_before_the_true_ground() -> None:
    for name, mirror_first in (("symmetric", True), ("symmetric-overlap", False)):
        plan = plan_scenario(name, 0)
        d1, d2 = (simulate_session(plan, s, i, 0) for i, s in enumerate(plan.sessions))
        xy_1, xy_2 = (np.array([[g.x, g.y] for g in d.ground_truth]) for d in (d1, d2))
        tree = cKDTree(xy_1)
        true_ground = np.flatnonzero(tree.query(xy_2)[0] < 1.0)
        mirror_ground = np.flatnonzero(tree.query(-xy_2)[0] < 1.0)  # B at p where A drove −p
        assert true_ground.size and mirror_ground.size
        assert (mirror_ground[0] < true_ground[0]) == mirror_first, name
        if not mirror_first:
            assert true_ground[0] == 0  # starts on session 1's ground
    assert plan.single is not None
    both = plan.sessions[0].spec.distance_m + plan.sessions[1].spec.distance_m
    assert plan.single.spec.distance_m == pytest.approx(both)


def test_bad_lookalike_parameters_are_input_errors() -> None:
    with pytest.raises(InputError, match="lookalike_m"):
        plan_scenario("twin", params={"lookalike_m": -1.0})
    with pytest.raises(InputError, match="symmetric_deg"):
        plan_scenario("symmetric", params={"symmetric_deg": 200.0})
    with pytest.raises(InputError, match="session2_laps"):
        plan_scenario("symmetric-overlap", params={"session2_laps": 0.0})


def test_twin_is_deterministic_per_seed_and_writes_its_ground_truth(tmp_path: Path) -> None:
    docs = [simulate("twin", tmp_path / name, seed=1, params={"lookalike_m": 5.0}, only=["session1"])
            for name in ("a", "b")]  # fmt: skip
    assert (tmp_path / "a" / "session1.bag").read_bytes() == (tmp_path / "b" / "session1.bag").read_bytes()
    other = _plan("twin", 2, lookalike_m=5.0).world  # another seed, another world
    assert not np.array_equal(other.p0, _plan("twin", 1, lookalike_m=5.0).world.p0)
    assert (tmp_path / "a" / "session1.tum").read_text() == (tmp_path / "b" / "session1.tum").read_text()
    scenario = json.loads((tmp_path / "a" / "scenario.json").read_text())
    assert scenario["preset"] == "circle" and scenario["lookalike"]["length_m"] == 5.0
    assert docs[0]["sessions"][1]["log"] is None  # only session 1 written


def _matching_frames(plan: Plan, seed: int) -> tuple[np.ndarray, list[int]]:
    """Session 2's frames that match a template of session 1 (built as the engine builds them)."""
    params = preset(plan.preset)
    store = LocalViewCells(params)
    views = []
    for index in (0, 1):
        drive = simulate_session(plan, plan.sessions[index], index, seed)
        views.append((drive, [store.make_template(image) for _, image in render_frames(plan, drive, seed, index)]))
    for template, mean in views[0][1]:
        best, error, _ = store.match(template, mean)
        if best < 0 or error > params.vt_match_threshold:
            store.add_templates(template[None], np.array([mean]))
    drive_2, views_2 = views[1]
    matched = [k for k, (t, m) in enumerate(views_2) if store.match(t, m)[1] <= params.vt_match_threshold]
    return drive_2.frame_poses, matched


def _longest_run(frames: list[int]) -> int:
    best = run = 0
    for k, frame in enumerate(frames):
        run = run + 1 if k and frame == frames[k - 1] + 1 else 1
        best = max(best, run)
    return best


@pytest.mark.slow
def test_twin_views_match_for_the_whole_stretch_and_only_there() -> None:
    seed, stretch = 0, 10.0
    plan = plan_scenario("twin", seed, params={"lookalike_m": stretch})
    poses, matched = _matching_frames(plan, seed)
    centre_2 = np.asarray(plan.info["lookalike"]["centres"][1])
    frames = stretch / 0.5  # frames 0.5 m apart
    assert frames - 1 <= _longest_run(matched) <= len(matched) <= frames + 3  # seed 0: one run of 21 frames
    for k in matched:  # on the stretch (or within a frame of it), heading east
        assert abs(poses[k, 0] - centre_2[0]) < stretch / 2 + 1.0 and abs(poses[k, 1] - centre_2[1]) < 0.8
        assert abs(wrap_angle_exact(poses[k, 3])) < math.radians(25)


@pytest.mark.slow
def test_symmetric_views_match_the_half_turned_track_only_in_a_symmetric_world() -> None:
    seed = 0
    plan = plan_scenario("symmetric", seed)
    poses, matched = _matching_frames(plan, seed)
    route_1 = plan.sessions[0].spec
    track_1 = route_1.route.position(np.linspace(route_1.start_m, route_1.start_m + route_1.distance_m, 400))
    tree = cKDTree(track_1)
    mirror = [k for k in matched if tree.query(-poses[k, :2])[0] < 1.5 and tree.query(poses[k, :2])[0] > 3.0]
    assert _longest_run(mirror) >= 3  # a false streak: the half-turned pose lies on session 1's track
    plain, matched_plain = _matching_frames(plan_scenario("symmetric", seed, params={"symmetric_deg": 0.0}), seed)
    assert not [k for k in matched_plain if tree.query(plain[k, :2])[0] > 3.0]  # no symmetry: only true ground

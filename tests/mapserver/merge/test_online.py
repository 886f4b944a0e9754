"""The online driver end to end on synthetic loop sessions (engine + merge, no store)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from core import Engine, Params, preset
from core.angles import wrap_angle
from core.se3 import compose, inverse
from mapserver.merge import OnlineMerger, StoredMap, verify
from mapserver.merge.hypotheses import MIN_TURN_RAD
from mapserver.merge.online import MergeEvent
from tests.mapserver.merge.sessions import PARAMS, map_stretch, run_session, true_alignment
from tests.mapserver.merge.world import LoopWorld

WORLD = LoopWorld(perimeter=40.0)


@pytest.fixture(scope="module")
def first_half() -> StoredMap:
    """Session 1: half a lap, arcs 0–20 m of the 40 m loop."""
    return map_stretch(WORLD, 0.0, 20.0, 1)


def _transform_error(record_transform: tuple[float, ...], truth: np.ndarray) -> tuple[float, float]:
    t = np.asarray(record_transform)
    return float(np.linalg.norm(t[:3] - truth[:3])), abs(float(wrap_angle(t[3] - truth[3])))


def _nn_rmse(a: np.ndarray, b: np.ndarray) -> float:
    """RMSE of each point of ``a`` to its nearest point of ``b`` (the paper's ICP comparison, aligned already)."""
    d = np.linalg.norm(a[:, None, :2] - b[None, :, :2], axis=2).min(axis=1)
    return float(np.sqrt(np.mean(d * d)))


def test_second_session_merges_once_and_maps_on_in_the_stored_map(first_half: StoredMap) -> None:
    run = run_session(WORLD, 24.0, 100.0, [first_half])
    assert len(run.events) == 1
    event = run.events[0]
    assert event.key == 1 and event.absorbed == ()
    assert event.record.confirmations >= PARAMS.merge_confirm
    # the transform between the sessions' frames is recovered (216° apart: a rotated session)
    truth = true_alignment(WORLD, 0.0, 24.0)
    gap, turn = _transform_error(event.record.transform, truth)
    assert gap < 0.3 and turn < 0.05
    # after the merge, ground mapped before (by session 1 or by session 2's partial map) is re-used
    frames, created = run.new_on_mapped_ground([(0.0, 20.0)])
    assert frames > 120 and created <= 0.05 * frames
    # the merged map is like the map of one session that drove the same route
    single = Engine(PARAMS)
    for image, motion, stamp in WORLD.drive(24.0, 100.0):
        single.step(image, motion, stamp)
    assert abs(run.engine.experience_count - single.experience_count) <= 0.1 * single.experience_count
    merged_world = compose(WORLD.pose(0.0), run.engine.map.poses)  # loaded frame → world
    single_world = compose(WORLD.pose(24.0), single.map.poses)
    extent = float(np.ptp(single_world[:, :2], axis=0).max())
    assert _nn_rmse(merged_world, single_world) <= 0.05 * extent
    origins = np.asarray(run.engine.map.snapshot()["em_origin"])
    assert set(np.unique(origins).tolist()) == {1, 9}


def test_a_merge_records_the_robots_pose_in_the_session_map_which_its_transform_carries_to_the_true_place(
    first_half: StoredMap,
) -> None:
    """``session_pose`` is where the session's own map had the robot when it merged: the transform takes it to
    where the merged engine has the robot, and that is where the robot truly was in the stored map's frame (the
    look-alike bench judges a merge's place by it)."""
    engine, driver = Engine(PARAMS, origin=9), OnlineMerger([first_half])
    merged_at: list[tuple[float, np.ndarray, np.ndarray]] = []
    arcs = WORLD.arc(24.0, 40.0)
    for arc, (image, motion, stamp) in zip(arcs, WORLD.drive(24.0, 40.0, t0=1000.0), strict=True):
        result = engine.step(image, motion, round(stamp * 1e9) * 1e-9)
        before = engine.map.robot_pose()
        event = driver.observe(engine, result, SimpleNamespace(image=image, motion=motion,
                                                               stamp_ns=round(stamp * 1e9)))
        if isinstance(event, MergeEvent):
            merged_at.append((float(arc), before, event.engine.map.robot_pose()))
            engine = event.engine
    assert len(merged_at) == 1 and len(driver.events) == 1
    arc, before, after = merged_at[0]
    event = driver.events[0]
    np.testing.assert_array_equal(event.session_pose, before)
    carried = compose(np.asarray(event.record.transform), event.session_pose)
    np.testing.assert_allclose(carried[:3], after[:3], atol=1e-9)
    assert abs(float(wrap_angle(carried[3] - after[3]))) < 1e-9
    truly = compose(inverse(WORLD.pose(0.0)), WORLD.pose(arc))  # the robot in session 1's map frame
    assert float(np.linalg.norm(carried[:2] - truly[:2])) < 0.3
    assert abs(float(wrap_angle(carried[3] - truly[3]))) < 0.05


def test_without_the_lattice_shift_mapped_ground_gets_new_experiences(first_half: StoredMap) -> None:
    """Operation (iii) disabled: the partial map's places are not found again (the paper's Fig. 12)."""
    shifted = run_session(WORLD, 24.0, 100.0, [first_half])
    unshifted = run_session(WORLD, 24.0, 100.0, [first_half], shift_lattice=False)
    assert len(unshifted.events) == 1 and not unshifted.events[0].record.lattice_shifted
    _, with_shift = shifted.new_on_mapped_ground([(0.0, 20.0)])
    frames, without_shift = unshifted.new_on_mapped_ground([(0.0, 20.0)])
    assert without_shift >= 6 and without_shift >= 3 * max(with_shift, 1)
    assert without_shift > 0.05 * frames


def test_a_session_started_at_90_degrees_still_merges_and_relocalises(first_half: StoredMap) -> None:
    run = run_session(WORLD, 30.0, 100.0, [first_half])  # 3/4 of a lap from session 1: frames 90° apart
    assert len(run.events) == 1
    record = run.events[0].record
    truth = true_alignment(WORLD, 0.0, 30.0)
    assert truth[3] == pytest.approx(-math.pi / 2)
    gap, turn = _transform_error(record.transform, truth)
    assert gap < 0.3 and turn < 0.05
    assert record.heading_offset_rad == pytest.approx(-math.pi / 2, abs=0.15)  # 36 heading cells: ±1.5 cells
    frames, created = run.new_on_mapped_ground([(0.0, 20.0)])
    assert created <= 0.05 * frames


def test_known_start_activates_the_stored_experience(first_half: StoredMap) -> None:
    """Scenario (i): a session starting on mapped ground joins the stored map with no partial map left."""
    stored_count = int(np.shape(first_half.state["em_pose"])[0])
    run = run_session(WORLD, 5.0, 30.0, [first_half])
    assert len(run.events) == 1
    # the merge waits for the evidence distance and the turn of MIN_TURN_RAD on the circle (0.5 m a frame), no longer
    needed = max(run.events[0].evidence["rule"]["evidence_m"], MIN_TURN_RAD * WORLD.perimeter / (2 * math.pi))
    assert needed / 0.5 <= run.merged_frames[0] <= needed / 0.5 + 2
    record = run.events[0].record
    assert record.experiences == stored_count  # everything the session had made was identified
    assert np.all(record.experience_map < stored_count)
    assert np.all(record.template_map < record.template_offset)
    frames, created = run.new_on_mapped_ground([(0.0, 20.0)])
    assert created <= 0.05 * frames
    assert run.engine.experience_count > stored_count  # and it mapped on beyond the stored stretch


def test_confirmation_rejects_a_look_alike_place() -> None:
    """A short look-alike stretch: K = 1 merges there by mistake (the paper's trigger); the default K does not."""
    world = LoopWorld(perimeter=40.0, alias=(2.0, 25.0, 5.5))  # arcs 25–30.5 look like arcs 2–7.5
    stored = map_stretch(world, 0.0, 20.0, 1)
    truth = true_alignment(world, 0.0, 22.0)
    eager = run_session(world, 22.0, 25.0, [stored], confirm=1, evidence_m=0.0, probation_m=0.0)  # the paper
    assert eager.events and eager.arcs[eager.merged_frames[0]] < 30.0  # merged inside the look-alike stretch
    gap, _ = _transform_error(eager.events[0].record.transform, truth)
    assert gap > 5.0
    one_match = run_session(world, 22.0, 25.0, [stored], confirm=1)  # K = 1, but the evidence test decides
    assert len(one_match.events) == 1 and one_match.arcs[one_match.merged_frames[0]] < 10.0
    careful = run_session(world, 22.0, 25.0, [stored])
    # at the real overlap, once the evidence distance is driven there
    assert len(careful.events) == 1 and careful.arcs[careful.merged_frames[0]] < 10.0
    gap, turn = _transform_error(careful.events[0].record.transform, truth)
    assert gap < 0.3 and turn < 0.05


def test_a_false_merge_is_rolled_back_by_its_verification_and_the_true_one_still_happens() -> None:
    """The paper's trigger merges inside the look-alike stretch; the probation sees the stored map's views
    fail where that merge predicts them, rolls it back to the session's own engine, and the session
    merges later at the real overlap."""
    world = LoopWorld(perimeter=40.0, alias=(2.0, 25.0, 5.5))
    stored = map_stretch(world, 0.0, 20.0, 1)
    truth = true_alignment(world, 0.0, 22.0)
    run = run_session(world, 22.0, 25.0, [stored], confirm=1, evidence_m=0.0)  # decision: the paper's; verified
    assert len(run.rollbacks) == 1
    rolled = run.rollbacks[0].event
    gap, _ = _transform_error(rolled.record.transform, truth)
    assert gap > 5.0  # it was the false merge
    verification = rolled.evidence["verification"]
    assert verification["status"] == "rejected" and verification["post_miss_m"] > 0
    assert run.arcs[run.rolled_back_frames[0]] < 40.0  # before the session reaches the real overlap
    assert len(run.events) == 1  # the true merge, after the rollback (on one match: within a frame's 0.5 m)
    gap, turn = _transform_error(run.events[0].record.transform, truth)
    assert gap < 0.6 and turn < 0.1
    # the session after the rollback is the engine that never merged: its first frames are the same map
    alone = Engine(PARAMS, origin=9)
    for image, motion, stamp in world.drive(22.0, 25.0, step=0.5, t0=1000.0):
        alone.step(image, motion, round(stamp * 1e9) * 1e-9)
    shadow = run.rollbacks[0].engine
    assert shadow.experience_count <= alone.experience_count
    n = shadow.experience_count
    np.testing.assert_array_equal(shadow.map.poses[:n], alone.map.poses[:n])


def test_the_engine_without_the_merge_steps_only_when_the_merge_is_rolled_back(
    first_half: StoredMap, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A merge that stands never steps the engine without it; one rolled back steps it through the
    probation's frames then, and gives the engine that stepping alongside gives (the memory bound set to 0
    bytes steps it on every frame)."""
    stepped: list[int] = []
    catch_up = verify.Probation.catch_up

    def counting(self: verify.Probation) -> Engine:
        stepped.append(len(self.pending))
        return catch_up(self)

    monkeypatch.setattr(verify.Probation, "catch_up", counting)
    kept = run_session(WORLD, 24.0, 31.0, [first_half])  # merged at arc 6, the log ends on the stored ground at 15
    probation = kept.driver.probation
    assert probation is not None and len(probation.pending) == probation.frames > 10
    assert kept.driver.finish() is None and kept.events[0].evidence["verification"]["status"] == "incomplete"
    passed = run_session(WORLD, 24.0, 100.0, [first_half])  # on past the stored half: its probation passes there
    assert passed.driver.finish() is None and passed.events[0].evidence["verification"]["status"] == "passed"
    assert stepped == []  # not one of their frames went through a second engine
    world = LoopWorld(perimeter=40.0, alias=(2.0, 25.0, 10.0))  # a 10 m look-alike: matches, then the truth
    stored = map_stretch(world, 0.0, 20.0, 1)
    lazy = run_session(world, 22.0, 25.0, [stored], confirm=1, evidence_m=0.0)
    held = len(lazy.rollbacks[0].seen)
    assert len(lazy.rollbacks) == 1 and stepped == [held] and held > 10  # all of the probation's frames, at once
    monkeypatch.setattr(verify, "LAZY_SHADOW_BYTES", 0)
    stepped.clear()
    eager = run_session(world, 22.0, 25.0, [stored], confirm=1, evidence_m=0.0)
    assert stepped[: held + 1] == [1] * held + [0]  # one frame at a time, nothing left at the rollback
    assert set(stepped[held + 1 :]) == {1}  # (and so the true merge's probation after it)
    a, b = lazy.rollbacks[0], eager.rollbacks[0]
    assert a.frame == b.frame and a.seen == b.seen and [c[:2] for c in a.created] == [c[:2] for c in b.created]
    assert lazy.merged_frames == eager.merged_frames  # the session after it: the same true merge, the same map
    np.testing.assert_array_equal(lazy.engine.map.poses, eager.engine.map.poses)
    np.testing.assert_array_equal(lazy.engine.snapshot()["lv_templates"], eager.engine.snapshot()["lv_templates"])


def test_a_log_that_ends_during_the_probation_keeps_the_merge_only_without_contradiction(
    first_half: StoredMap,
) -> None:
    """Session 2 merges at the real overlap (arc 6 of the next lap) and its log ends 1 m later: what the
    probation saw speaks for the merge, so it stays, its verification cut short; had the views disagreed
    with it, the log's end rolls it back to the engine that never merged."""
    for contradicted in (False, True):
        run = run_session(WORLD, 22.0, 25.0, [first_half])
        driver = run.driver
        assert driver is not None and len(run.events) == 1 and driver.probation is not None  # the log ends in it
        event = run.events[0]
        hypothesis = driver.probation.hypothesis
        assert hypothesis.post_hit_m > 0 == hypothesis.post_miss_m
        if contradicted:
            hypothesis.post_miss_m = hypothesis.post_hit_m / 2.0 + 0.1  # net −0.2 m
        rollback = driver.finish()
        assert driver.probation is None
        if not contradicted:
            assert rollback is None and driver.events == [event]
            verification = event.evidence["verification"]
            assert verification["status"] == "incomplete" and verification["since_match_m"] < 1.0
            continue
        assert rollback is not None and rollback.event is event and driver.events == []
        assert event.evidence["verification"]["status"] == "rejected" and driver.rollbacks == [rollback]
        alone = Engine(PARAMS, origin=9)  # the engine to go on with is the session without the merge
        for image, motion, stamp in WORLD.drive(22.0, 25.0, step=0.5, t0=1000.0):
            alone.step(image, motion, round(stamp * 1e9) * 1e-9)
        assert rollback.engine.experience_count == alone.experience_count
        np.testing.assert_array_equal(rollback.engine.map.poses, alone.map.poses)

def test_a_session_bridging_two_maps_joins_them() -> None:
    """New College case: one session merges into map A, then the merged engine into map B."""
    a = map_stretch(WORLD, 0.0, 12.0, 1)
    b = map_stretch(WORLD, 22.0, 12.0, 2)
    run = run_session(WORLD, 0.0, 38.0, [a, b], origin=3)
    assert [e.key for e in run.events] == [1, 2]
    assert run.events[1].absorbed == (1,)
    # leaving A's ground: the probation's prediction leaves A's edge with the robot (unmapped ground, no trials);
    # re-anchoring on A's last places would make a run of mismatches that holds it open (Probation.held_open) until
    # the session merges into B; either way it passes and does not block that merge
    first = run.events[0].evidence["verification"]
    assert first["status"] == "passed"
    engine = run.engine
    origins = np.asarray(engine.map.snapshot()["em_origin"])
    assert set(np.unique(origins).tolist()) == {1, 2, 3}
    # the last merge keeps B's ids first; A and the session follow, all in B's frame
    second = run.events[1].record
    assert second.experience_offset == int(np.shape(b.state["em_pose"])[0])
    from_a, from_b = int(np.flatnonzero(origins == 1)[0]), int(np.flatnonzero(origins == 2)[-1])
    path = engine.shortest_path(from_a, from_b, "distance")
    assert path.nodes[0] == from_a and path.nodes[-1] == from_b
    # A's first place and B's last are 6.4 m apart on the loop... as the world says (B's frame = world at 22 m)
    truth = np.linalg.norm(WORLD.pose(0.0)[:2] - WORLD.pose(33.5)[:2])
    place_a = compose(WORLD.pose(22.0), engine.map.poses[from_a])
    assert float(np.linalg.norm(place_a[:2] - WORLD.pose(0.0)[:2])) < 0.5
    assert float(np.linalg.norm(engine.map.poses[from_a, :2] - engine.map.poses[from_b, :2])) == pytest.approx(
        truth, abs=0.5
    )


def test_incompatible_stored_maps_are_skipped(first_half: StoredMap) -> None:
    other = StoredMap("big", PARAMS.replace(pc_dim_xy=51), first_half.state)
    driver = OnlineMerger([other, first_half])
    engine = Engine(PARAMS, origin=9)
    for image, motion, stamp in WORLD.drive(24.0, 2.0):
        driver.observe(engine, engine.step(image, motion, stamp))
    assert "lattices differ" in driver.skipped["big"]
    assert driver.candidates == [1]


def test_confirmation_default_comes_from_the_parameters(first_half: StoredMap) -> None:
    for k in (1, 4):  # with no evidence distance, K supporting matches decide
        params: Params = PARAMS.replace(merge_confirm=k, merge_evidence_m=0.0, merge_probation_m=0.0)
        run = run_session(WORLD, 24.0, 20.0, [StoredMap(1, params, first_half.state)], params=params)
        assert run.events and run.events[0].record.confirmations == k


@pytest.mark.slow
def test_4dof_session_merges_with_depth() -> None:
    """PoseidonSLAM lattice (x, y, z, θ) and 4-DoF experiences on a loop that goes up and down (LVC views)."""
    params = preset("poseidon-lvc")
    world = LoopWorld(perimeter=4.0, px_per_m=80.0, height=24, width=64, depth=0.3, seed=4)
    step = 0.025
    stored = map_stretch(world, 0.0, 3.0, 1, params=params, step=step)
    run = run_session(world, 3.3, 8.0, [stored], params=params, step=step)
    assert len(run.events) == 1
    record = run.events[0].record
    truth = true_alignment(world, 0.0, 3.3)
    assert abs(record.transform[2] - truth[2]) < 0.05  # the depth offset between the sessions' frames
    gap, turn = _transform_error(record.transform, truth)
    assert gap < 0.1 and turn < 0.15
    assert len(record.lattice_offset) == 4
    # merged depths agree with ground truth as well as a single session's do
    def depth_rmse(engine: Engine, starts: dict[int, tuple[float, float]], frame: float) -> float:
        """Experience z against the true z of its place (arc from its origin's start and stamp)."""
        snap = engine.map.snapshot()
        errors = []
        for origin, (start, t0) in starts.items():
            mine = snap["em_origin"] == origin
            arcs = start + (snap["em_stamp"][mine] - t0) / 0.5 * step
            true_z = np.array([world.pose(a)[2] for a in arcs]) - world.pose(frame)[2]
            errors.append(snap["em_pose"][mine, 2] - true_z)
        e = np.concatenate(errors)
        return float(np.sqrt(np.mean(e * e)))

    single = Engine(params, origin=9)
    for image, motion, stamp in world.drive(3.3, 8.0, step=step, t0=1000.0):
        single.step(image, motion, stamp)
    merged_rmse = depth_rmse(run.engine, {1: (0.0, 0.0), 9: (3.3, 1000.0)}, 0.0)
    single_rmse = depth_rmse(single, {9: (3.3, 1000.0)}, 3.3)
    assert merged_rmse <= max(1.5 * single_rmse, 0.02)
    frames, created = run.new_on_mapped_ground([(0.0, 3.0)])
    assert created <= 0.1 * frames


def test_after_an_online_merge_only_the_stored_maps_links_count_as_a_finished_sessions() -> None:
    """``em_stored_links`` (the links :func:`core.robust.switch_off_outliers` weighs new links against and gives the
    stored prior): an online merge keeps the running session's own links, but they stay the running session's —
    not a finished map's — until the session ends and its map settles. Before 2026-11-30 a merge's restore counted
    them as stored. Must still: the stored map's links stay stored, and at the session's end every link is."""
    stored_engine = Engine(PARAMS, origin=1)
    for image, motion, stamp in WORLD.drive(0.0, 20.0):
        stored_engine.step(image, motion, stamp)
    stored_engine.settle()  # a finished session's map, as the store holds it
    stored = StoredMap(1, PARAMS, stored_engine.snapshot())
    stored_count = int(np.shape(stored.state["em_link_from"])[0])
    assert int(stored.state["em_stored_links"]) == stored_count > 0
    engine, driver = Engine(PARAMS, origin=9), OnlineMerger([stored])
    own_links = merged_stored = -1
    for image, motion, stamp in WORLD.drive(24.0, 40.0, t0=1000.0):
        result = engine.step(image, motion, round(stamp * 1e9) * 1e-9)
        links_before = engine.map.link_count
        event = driver.observe(engine, result, SimpleNamespace(image=image, motion=motion,
                                                               stamp_ns=round(stamp * 1e9)))  # fmt: skip
        if isinstance(event, MergeEvent):
            own_links, engine = links_before, event.engine
            merged_stored = int(engine.snapshot()["em_stored_links"])
    assert len(driver.events) == 1 and own_links > 0  # the session had links of its own when it merged
    assert engine.map.link_count > stored_count + 1
    assert merged_stored == stored_count  # the stored map's links, not the running session's
    engine.settle()
    assert int(engine.snapshot()["em_stored_links"]) == engine.map.link_count  # a finished session's map

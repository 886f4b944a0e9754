"""Relaxation: bounded per-frame work, and the settled map equal to full relaxation (stated tolerance).

Stated tolerance: after ``settle()`` every experience is within 1e-6 (metres, radians) of the
fixed point of full relaxation — every link, iterated until the largest correction is below
1e-13 — and of the independent dense least-squares solution of the same normal equations.
"""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core import Engine
from core.angles import wrap_angle, wrap_angle_below_pi, wrap_angle_exact
from core.config import Params
from core.experience_map import ExperienceMap, LinkKind
from core.motion import Motion
from core.relaxation import (
    COMPILED_FROM,
    LinkComponents,
    SwitchedRelaxation,
    cycle_links,
    residuals,
    solve,
    subtree_sums,
)
from core.se3 import relative_step
from tests.core.conftest import departing
from tests.worlds import StripWorld

TOLERANCE = 1e-6


def _params(**changes: object) -> Params:
    return departing().replace(**{"exp_initial_em_deg": 0.0, "exp_loops": 10, **changes})


def _square_laps(params: Params, laps: int = 3, relax_every_frame: bool = True) -> ExperienceMap:
    """Three laps of an 8 m square with biased odometry (scale, yaw, climb); lap 2 and 3 corners close loops.

    Every lap-1 corner is revisited: the robot links to it and continues from it (the engine's CREATE_EDGE
    then set), so each later lap adds four loop closures with a misclosure that grows along the lap.
    """
    em = ExperienceMap(params, 3)
    em.create_experience(0, np.zeros(3), 0.0, 0)
    corners: dict[int, int] = {0: 0}
    stamp = 0.0
    for lap in range(laps):
        for side in range(4):
            for step in range(8):
                turn = math.pi / 2 + 0.03 if step == 7 else 0.004  # biased heading
                em.on_odo(Motion(1.03, 0.01, 0.02, turn, 1.0))  # 3 % long, drifting left and up
                stamp += 1.0
                index = side * 8 + step + 1
                corner = index % 8 == 0
                if lap > 0 and corner:
                    target = corners[index % 32]
                    assert em.create_link(em.current, target, 0.0, LinkKind.LOOP)
                    em.set_experience(target, 0.0)
                else:
                    new = em.create_experience(1, np.zeros(3), stamp, 0)
                    if lap == 0 and corner and index < 32:
                        corners[index] = new
                if relax_every_frame:
                    em.relax_step()
    return em


def _least_squares(em: ExperienceMap, start: np.ndarray) -> np.ndarray:
    """Independent dense solution: headings, then positions, by numpy lstsq with experience 0 fixed."""
    src, dst, t, _, _, _ = em.links
    n = em.count
    a = np.zeros((src.size, n))
    a[np.arange(src.size), dst] = 1.0
    a[np.arange(src.size), src] = -1.0
    winding = np.round((start[dst, 3] - start[src, 3] - t[:, 3]) / (2 * math.pi))
    yaw_meas = t[:, 3] + 2 * math.pi * winding - a[:, 0] * start[0, 3]
    yaw = np.empty(n)
    yaw[0] = start[0, 3]
    yaw[1:] = np.linalg.lstsq(a[:, 1:], yaw_meas, rcond=None)[0]
    c, s = np.cos(yaw[src]), np.sin(yaw[src])
    meas = np.stack([c * t[:, 0] - s * t[:, 1], s * t[:, 0] + c * t[:, 1], t[:, 2]], axis=1)
    out = np.empty((n, 4))
    out[0] = start[0]
    out[1:, :3] = np.linalg.lstsq(a[:, 1:], meas - a[:, :1] * start[0, :3], rcond=None)[0]
    out[:, 3] = wrap_angle_below_pi(yaw)
    return out


def _pose_error(a: np.ndarray, b: np.ndarray) -> float:
    diff = a - b
    diff[:, 3] = wrap_angle_below_pi(diff[:, 3])
    return float(np.abs(diff).max())


def test_settled_map_equals_full_relaxation_and_least_squares() -> None:
    dead_reckoned = _square_laps(_params(), relax_every_frame=False)
    assert float(np.abs(dead_reckoned.full_corrections()).max()) > 0.05  # the laps really disagree
    em = _square_laps(_params(exp_relax_batch=2))  # a small per-frame budget leaves work for settle()
    assert int(np.sum(em.links[5] == LinkKind.LOOP)) == 8
    before = em.snapshot()
    assert em.relax_pending
    em.settle()
    # reference 1: full relaxation (all links, simultaneous Jacobi) iterated to convergence from the same state
    full = ExperienceMap.restore(_params(exp_relax_tolerance=1e-13), 3, before)
    iterations = full.relax(iterations=200_000)
    assert iterations < 200_000
    assert _pose_error(em.poses, full.poses) <= TOLERANCE
    # reference 2: dense least squares of the normal equations
    assert _pose_error(em.poses, _least_squares(em, before["em_pose"].reshape(-1, 4))) <= TOLERANCE
    assert float(np.abs(em.full_corrections()).max()) <= em.params.exp_relax_tolerance
    assert em.poses[0] == pytest.approx(before["em_pose"].reshape(-1, 4)[0])  # the anchor did not move


def test_the_settled_map_does_not_depend_on_the_per_frame_budget() -> None:
    """Links hold the odometry as measured, so only the path to the fixed point depends on the budget."""
    maps = {batch: _square_laps(_params(exp_relax_batch=batch)) for batch in (1, 3, 16, 4096)}
    maps[0] = _square_laps(_params(), relax_every_frame=False)
    for em in maps.values():
        em.settle()
    reference = maps[4096]
    for em in maps.values():
        assert _pose_error(em.poses, reference.poses) <= 1e-9
        assert np.allclose(em.links[2], reference.links[2], atol=1e-12)


def test_per_frame_work_is_bounded_by_the_batch_whatever_the_map_size() -> None:
    for n in (300, 3000):
        em = ExperienceMap(_params(exp_relax_batch=32), 3)
        em.create_experience(0, np.zeros(3), 0.0, 0)
        for i in range(1, n):
            em.on_odo(Motion(1.0, 0.0, 0.0, 2 * math.pi / n, 1.0))
            em.create_experience(i, np.zeros(3), float(i), 0)
        em.on_odo(Motion(1.5, 0.0, 0.3, 2 * math.pi / n, 1.0))  # 0.5 m long and 0.3 m high at the closure
        em.create_link(em.current, 0, 0.0, LinkKind.LOOP)
        counts = [em.relax_step() for _ in range(200)]
        assert max(counts) <= 32
        assert sum(counts) > 0


def test_an_empty_worklist_means_every_correction_is_within_the_tolerance() -> None:
    em = ExperienceMap(_params(exp_relax_batch=24, exp_relax_tolerance=1e-3), 3)
    em.create_experience(0, np.zeros(3), 0.0, 0)
    for i in range(1, 120):
        em.on_odo(Motion(1.0, 0.0, 0.0, 2 * math.pi / 120, 1.0))
        em.create_experience(i, np.zeros(3), float(i), 0)
    em.on_odo(Motion(1.4, 0.0, 0.1, 2 * math.pi / 120 + 0.02, 1.0))
    em.create_link(em.current, 0, 0.0, LinkKind.LOOP)
    frames = 0
    while em.relax_pending and frames < 20_000:
        em.relax_step()
        frames += 1
    assert not em.relax_pending
    assert float(np.abs(em.full_corrections()).max()) <= 1e-3


def test_engine_run_settles_to_full_relaxation(strip_world: StripWorld) -> None:
    params = _params(
        template_x_size=32, template_y_size=12, vt_shift_match=2, vt_step_match=1, vt_match_threshold=0.03,
        pc_dim_xy=21, pc_dim_th=36, exp_delta_pc_threshold=2.0, vt_min_inject_age=5, exp_relax_batch=4,
    )
    engine = Engine(params)
    for image, motion, stamp in strip_world.drive(laps=2.5, yaw_bias=0.02):
        engine.step(image, motion, stamp)
    assert engine.loop_closures >= 1
    before = engine.snapshot()
    engine.settle()
    full = ExperienceMap.restore(params.replace(exp_relax_tolerance=1e-13), 3, before)
    full.relax(iterations=200_000)
    assert _pose_error(engine.map.poses, full.poses) <= TOLERANCE
    assert not engine.map.relax_pending


def test_anchor_per_component_and_joining_components() -> None:
    em = ExperienceMap(_params(), 3)
    em.create_experience(0, np.zeros(3), 0.0, 0)
    em.on_odo(Motion(2.0, 0.0, 0.0, 0.0, 1.0))
    em.create_experience(1, np.zeros(3), 1.0, 0)
    # a second, unlinked part of the map (as a merge may append): experiences 2 and 3
    state = em.snapshot()
    state["em_pose"] = np.vstack([state["em_pose"], [[10.0, 0.0, 0.0, 0.0], [12.5, 0.0, 0.0, 0.0]]])
    state["em_pc"] = np.vstack([state["em_pc"], np.zeros((2, 3))])
    for key, extra in (("em_template", [2, 3]), ("em_origin", [1, 1])):
        state[key] = np.concatenate([state[key], extra])
    state["em_stamp"] = np.concatenate([state["em_stamp"], [0.0, 1.0]])
    for key, extra in (("em_link_from", [2]), ("em_link_to", [3]), ("em_link_kind", [0])):
        state[key] = np.concatenate([state[key], np.asarray(extra, dtype=state[key].dtype)])
    state["em_link_transform"] = np.vstack([state["em_link_transform"], [[2.0, 0.0, 0.0, 0.0]]])
    state["em_link_dt"] = np.concatenate([state["em_link_dt"], [1.0]])
    state["em_link_distance"] = np.concatenate([state["em_link_distance"], [2.0]])
    joined = ExperienceMap.restore(em.params, 3, state)
    assert joined.anchors().tolist() == [True, False, True, False]
    joined.settle()  # each part settles against its own anchor: 3 moves to 12.0, 2 stays
    assert joined.poses[2, 0] == pytest.approx(10.0) and joined.poses[3, 0] == pytest.approx(12.0)
    assert joined.add_link_raw(1, 2, np.array([7.0, 0.0, 0.0, 0.0]), 1.0, 7.0, LinkKind.MERGE)
    assert joined.anchors().tolist() == [True, False, False, False]
    assert joined.relax_pending
    joined.settle()
    # one chain 0 → 1 → 2 → 3 measured 2, 7, 2 m: consistent, so it is laid out exactly from the anchor
    assert joined.poses[:, 0] == pytest.approx([0.0, 2.0, 9.0, 11.0], abs=1e-9)


def test_clamps_limit_how_far_a_frame_moves_an_experience() -> None:
    em = ExperienceMap(_params(max_correction_step=0.05, exp_relax_batch=64), 3)
    em.create_experience(0, np.zeros(3), 0.0, 0)
    for i in range(1, 10):
        em.on_odo(Motion(1.0, 0.0, 0.0, 0.0, 1.0))
        em.create_experience(i, np.zeros(3), float(i), 0)
    em.add_link_raw(9, 0, np.array([-8.0, 0.0, 0.0, 0.0]), 1.0, 8.0, LinkKind.MANUAL)  # 1 m inconsistent
    for _ in range(5):
        before = em.poses.copy()
        em.relax_step()
        moved = np.linalg.norm(em.poses[:, :3] - before[:, :3], axis=1)
        assert moved.max() <= 0.05 + 1e-12
    assert moved.max() == pytest.approx(0.05)
    em.settle()  # the clamps limit the speed, not the destination
    assert em.poses[9, 0] == pytest.approx(9.0 - 9 * 1.0 / 10, abs=1e-9)  # 1 m spread over 10 links


def test_exp_loops_zero_switches_relaxation_off() -> None:
    em = _square_laps(_params(exp_loops=0))
    before = em.poses.copy()
    assert em.relax_step() == 0
    assert em.settle() == 0
    assert np.array_equal(em.poses, before)


def test_worklist_survives_a_snapshot_and_the_key_is_optional() -> None:
    params = _params(exp_relax_batch=2)
    em = _square_laps(params)
    assert em.relax_pending
    state = em.snapshot()
    buffer = io.BytesIO()
    np.savez(buffer, **state)
    buffer.seek(0)
    with np.load(buffer) as data:
        back = ExperienceMap.restore(params, 3, {key: data[key] for key in data.files})
    assert np.array_equal(back.relax_queue, em.relax_queue)
    for _ in range(20):
        em.relax_step()
        back.relax_step()
    assert np.array_equal(back.poses, em.poses)
    legacy = {key: value for key, value in state.items() if key != "em_relax_queue"}
    scheduled = ExperienceMap.restore(params, 3, legacy)
    assert scheduled.relax_queue.tolist() == list(range(em.count))  # pending without a queue: everyone
    legacy["em_relax_pending"] = np.asarray(False)
    assert not ExperienceMap.restore(params, 3, legacy).relax_pending


def _octagon_with_a_turned_closure(turn_error: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Eight experiences on a regular octagon of 2 m sides rising 0.1 m per side, exact odometry links between
    neighbours, and a closure 7 → 0 whose translation is right but whose heading is ``turn_error`` off (a forward
    view matched a little round) and whose height misses by 0.3 m. Returns (pose, src, dst, transform)."""
    yaw = np.arange(8) * math.pi / 4
    xy = np.cumsum(np.stack([2 * np.cos(yaw), 2 * np.sin(yaw)], axis=1), axis=0) - [2.0, 0.0]
    truth = np.column_stack([xy, 0.1 * np.arange(8), yaw])
    src, dst = np.arange(8), (np.arange(8) + 1) % 8
    transform = np.zeros((8, 4))
    for k, (i, j) in enumerate(zip(src, dst, strict=True)):
        transform[k] = [*relative_step(truth[i], truth[j])[:3], wrap_angle_exact(truth[j, 3] - truth[i, 3])]
    transform[7, 2] += 0.3
    transform[7, 3] += turn_error
    return truth, src, dst, transform


def test_the_joint_refinement_reaches_the_least_squares_an_independent_solver_finds() -> None:
    """``refine_jointly`` from RatSLAM's fixed point against scipy's trust-region least squares on the same
    objective (Σ‖r_xyz‖² + (w·r_ψ)², experience 0 fixed): the same poses to 1e-6, a lower cost than the fixed
    point's (whose headings absorb the closure's 0.2 rad alone, so it misses in position), and the anchor kept."""
    from scipy.optimize import least_squares

    from core.relaxation import refine_jointly, residuals, solve

    truth, src, dst, transform = _octagon_with_a_turned_closure(0.2)
    anchor = np.zeros(8, dtype=bool)
    anchor[0] = True
    weight = 0.7
    fixed_point = solve(truth, src, dst, transform, anchor)
    joint = refine_jointly(fixed_point, src, dst, transform, anchor, heading_weight=weight, iterations=20)

    def cost(pose: np.ndarray) -> float:
        r = residuals(pose, src, dst, transform)
        return float(np.sum(r[:, :3] ** 2) + np.sum((weight * r[:, 3]) ** 2))

    def stacked(free: np.ndarray) -> np.ndarray:
        pose = np.vstack([truth[:1], free.reshape(7, 4)])
        r = residuals(pose, src, dst, transform)
        r[:, 3] *= weight
        return r.reshape(-1)

    reference = least_squares(stacked, fixed_point[1:].reshape(-1), xtol=1e-14, ftol=1e-14, gtol=1e-14).x
    np.testing.assert_allclose(joint[1:], reference.reshape(7, 4), atol=1e-6)
    np.testing.assert_array_equal(joint[0], truth[0])
    assert cost(joint) < 0.5 * cost(fixed_point)
    np.testing.assert_allclose(joint[:, 2], fixed_point[:, 2], atol=1e-9)  # heights do not turn: as solved


def test_the_joint_refinement_leaves_a_consistent_graph_where_it_is() -> None:
    """The must-still-hold pair: exact links (no heading error, no height miss) give back the truth unchanged."""
    from core.relaxation import refine_jointly

    truth, src, dst, transform = _octagon_with_a_turned_closure(0.0)
    transform[7, 2] -= 0.3
    anchor = np.zeros(8, dtype=bool)
    anchor[0] = True
    joint = refine_jointly(truth, src, dst, transform, anchor)
    np.testing.assert_allclose(joint[:, :3], truth[:, :3], atol=1e-12)
    np.testing.assert_allclose(wrap_angle(joint[:, 3] - truth[:, 3]), 0.0, atol=1e-12)


@pytest.mark.parametrize(("weighted", "end"), [(False, 100.0 / 11.0), (True, 9.5)])
def test_a_long_link_weighs_as_the_odometry_it_spans_in_the_joint_refinement(weighted: bool, end: float) -> None:
    """Ten 1 m odometry links along x and one 10 m link from the first experience to the last that says 9 m
    (a reckoning link 1 m off). Least squares over the total T: unit weights give 10·(T/10 − 1)² + (T − 9)²,
    minimal at T = 100/11; with the long link's variance ten links' worth (w² = 1/10, ``length_weights``)
    (T/10 − 1)·2 + 0.2·(T − 9) = 0, T = 9.5: the chain and the link trusted alike, as each spans 10 m."""
    from core.relaxation import length_weights, refine_jointly

    pose = np.zeros((11, 4))
    pose[:, 0] = np.arange(11.0)
    src, dst = np.append(np.arange(10), 0), np.append(np.arange(1, 11), 10)
    transform = np.zeros((11, 4))
    transform[:10, 0] = 1.0
    transform[10, 0] = 9.0
    distance = np.append(np.ones(10), 10.0)
    assert length_weights(distance, 1.0).tolist() == pytest.approx([1.0] * 10 + [math.sqrt(0.1)])
    anchor = np.zeros(11, dtype=bool)
    anchor[0] = True
    weight = length_weights(distance, 1.0) if weighted else None
    joint = refine_jointly(pose, src, dst, transform, anchor, weight=weight)
    assert joint[10, 0] == pytest.approx(end, abs=1e-9)
    np.testing.assert_allclose(np.diff(joint[:, 0]), end / 10.0, atol=1e-9)  # the chain stretches evenly


# ---------------------------------------------------------------- the robust check's low-rank solve


@st.composite
def _random_graph(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A random tree of fixed links (odometry) and extra links between random ends; poses and switchable mask.

    Returns (pose, src, dst, transform, fixed): the tree links come first; some of them are switchable too.
    """
    n = draw(st.integers(2, 24))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    parent = np.array([rng.integers(0, i) for i in range(1, n)], dtype=np.int64)
    extra = draw(st.integers(0, 2 * n))
    a = rng.integers(0, n, extra)
    b = (a + rng.integers(1, n, extra)) % n  # never a self-loop
    src = np.concatenate([parent, a])
    dst = np.concatenate([np.arange(1, n), b])
    transform = np.column_stack([rng.uniform(-2, 2, src.size), rng.uniform(-2, 2, src.size),
                                 rng.uniform(-0.3, 0.3, src.size), rng.uniform(-3, 3, src.size)])  # fmt: skip
    pose = np.column_stack([rng.uniform(-5, 5, (n, 3)), rng.uniform(-math.pi, math.pi, n)])
    fixed = np.zeros(src.size, dtype=bool)
    fixed[: n - 1] = rng.random(n - 1) < draw(st.sampled_from([0.5, 0.9, 1.0]))
    return pose, src, dst, transform, fixed


@st.composite
def _laps_graph(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A route of fixed links (odometry) with closures between random places: long runs between the closures.

    Some closures are fixed too (chords the search never switches), and the route's links point either way.
    Returns (pose, src, dst, transform, fixed) as :func:`_random_graph`.
    """
    n = draw(st.integers(3, 60))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    closures = draw(st.integers(0, max(1, n // 4)))
    a = rng.integers(0, n, closures)
    b = (a + rng.integers(2, n, closures)) % n
    flip = rng.random(n - 1) < 0.2
    src = np.concatenate([np.where(flip, np.arange(1, n), np.arange(n - 1)), a])
    dst = np.concatenate([np.where(flip, np.arange(n - 1), np.arange(1, n)), b])
    transform = np.column_stack([rng.uniform(-2, 2, src.size), rng.uniform(-2, 2, src.size),
                                 rng.uniform(-0.3, 0.3, src.size) * draw(st.sampled_from([0.0, 1.0])),
                                 rng.uniform(-3, 3, src.size)])  # fmt: skip
    pose = np.column_stack([rng.uniform(-5, 5, (n, 3)), rng.uniform(-math.pi, math.pi, n)])
    fixed = np.concatenate([np.ones(n - 1, dtype=bool), rng.random(closures) < 0.3])
    return pose, src, dst, transform, fixed


def _exact_link_residuals(pose: np.ndarray, src: np.ndarray, dst: np.ndarray, transform: np.ndarray,
                          active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The old computation: the full solve over ``active`` (solve, passes=1), then every link's residual."""
    on = np.flatnonzero(active)
    solved = solve(pose, src[on], dst[on], transform[on], _anchors(pose.shape[0], src, dst), passes=1)
    res = residuals(solved, src, dst, transform)
    return np.linalg.norm(res[:, :3], axis=1), res[:, 3]


def _anchors(n: int, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Each connected part's lowest experience (as core.robust.component_anchors, computed by hand)."""
    label = np.arange(n)
    for _ in range(n):  # label propagation: the lowest id reachable
        for a, b in zip(src.tolist(), dst.tolist(), strict=True):
            label[a] = label[b] = min(label[a], label[b])
    return label == np.arange(n)


def _whole_by_count(n: int, src: np.ndarray, dst: np.ndarray, active: np.ndarray) -> bool:
    """Whether ``active`` joins what all the links join: union-find by hand, component counts compared."""

    def parts(links: np.ndarray) -> int:
        root = list(range(n))

        def find(i: int) -> int:
            while root[i] != i:
                i = root[i]
            return i

        for link in links.tolist():
            root[find(int(src[link]))] = find(int(dst[link]))
        return len({find(i) for i in range(n)})

    return parts(np.flatnonzero(active)) == parts(np.arange(src.size))


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 60), st.integers(0, 2**31 - 1))
def test_subtree_sums_are_the_sums_over_each_nodes_descendants(n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    parent = np.arange(n)
    for i in range(1, n):
        if rng.random() < 0.9:  # otherwise i roots a tree of its own
            parent[i] = rng.integers(0, i)
    value = rng.normal(size=n)
    expected = np.zeros(n)
    for i in range(n):  # walk up from each node, adding its value to itself and every ancestor
        j = i
        expected[j] += value[i]
        while parent[j] != j:
            j = parent[j]
            expected[j] += value[i]
    assert subtree_sums(parent, value) == pytest.approx(expected, abs=1e-9)


@settings(max_examples=60, deadline=None)
@given(_random_graph())
def test_cycle_links_are_what_peeling_the_leaves_leaves(graph: tuple[np.ndarray, ...]) -> None:
    pose, src, dst, _, _ = graph
    n = pose.shape[0]
    alive = np.ones(src.size, dtype=bool)
    changed = True
    while changed:  # the 2-core: take away the links of experiences with one link until none is left
        degree = np.bincount(np.concatenate([src[alive], dst[alive]]), minlength=n)
        leaf = alive & ((degree[src] == 1) | (degree[dst] == 1))
        changed = bool(leaf.any())
        alive &= ~leaf
    assert cycle_links(n, src, dst).tolist() == alive.tolist()


def test_cycle_links_of_a_cycle_with_a_tail_and_a_pair_of_parallel_links() -> None:
    # 0-1-2-0 a triangle, 2-3-4 a tail, 5=6 two links between the same pair, 7 alone
    src = np.array([0, 1, 2, 2, 3, 5, 6])
    dst = np.array([1, 2, 0, 3, 4, 6, 5])
    assert cycle_links(8, src, dst).tolist() == [True, True, True, False, False, True, True]
    assert not cycle_links(8, src[:5][[0, 1, 3, 4]], dst[:5][[0, 1, 3, 4]]).any()  # a tree has none


@settings(max_examples=60, deadline=None)
@given(_random_graph(), st.integers(0, 2**31 - 1))
def test_link_components_tell_whole_sets_as_a_count_does(graph: tuple[np.ndarray, ...], seed: int) -> None:
    pose, src, dst, _, fixed = graph
    n = pose.shape[0]
    rng = np.random.default_rng(seed)
    parts = LinkComponents(n, src, dst, fixed)
    for _ in range(6):
        active = fixed | (rng.random(src.size) < rng.uniform(0.2, 1.0))
        assert parts.whole(active) == _whole_by_count(n, src, dst, active)
    # and must not: a fixed link off is never whole, though the rest may join the graph as all links do
    if fixed.any():
        active = np.ones(src.size, dtype=bool)
        active[np.flatnonzero(fixed)[0]] = False
        assert not parts.whole(active)


def test_a_set_less_one_link_on_a_cycle_is_known_whole_without_a_count() -> None:
    src, dst = np.array([0, 1, 2, 2]), np.array([1, 2, 0, 3])  # a triangle and a tail
    parts = LinkComponents(4, src, dst, np.zeros(4, dtype=bool))
    every = np.ones(4, dtype=bool)
    assert parts.whole(every)
    counted: list[bool] = []
    count = parts.labels
    parts.labels = lambda active: counted.append(True) or count(active)  # type: ignore[method-assign]
    z = np.array([0.5, 0.5, 0.5, 0.0])  # the triangle's links pull; the tail's (a bridge) does not
    assert parts.whole(np.array([False, True, True, True]), (every, z))
    assert not counted
    # must count: the bridge is no cycle link, and without it the set is not whole
    assert not parts.whole(np.array([True, True, True, False]), (every, z))
    assert counted == [True]


@settings(max_examples=80, deadline=None)
@given(_random_graph(), st.integers(0, 2**31 - 1), st.sampled_from([0, 2, 24]))
def test_the_low_rank_solve_gives_the_full_solves_residuals(
    graph: tuple[np.ndarray, ...], seed: int, rebase: int
) -> None:
    """Differential: a run of random switches against the full solve of each; ``rebase`` 0 factorises every set."""
    _compare_with_full_solves(graph, seed, rebase)


@settings(max_examples=60, deadline=None)
@given(_laps_graph(), st.integers(0, 2**31 - 1), st.sampled_from([0, 24]))
def test_the_low_rank_solve_gives_the_full_solves_residuals_along_long_runs(
    graph: tuple[np.ndarray, ...], seed: int, rebase: int
) -> None:
    """The same on routes with few closures: runs of many fixed links, some pointing against the run."""
    _compare_with_full_solves(graph, seed, rebase)


def _compare_with_full_solves(graph: tuple[np.ndarray, ...], seed: int, rebase: int) -> None:
    pose, src, dst, transform, fixed = graph
    n = pose.shape[0]
    rng = np.random.default_rng(seed)
    anchor = _anchors(n, src, dst)
    switched = SwitchedRelaxation(pose, src, dst, transform, anchor, LinkComponents(n, src, dst, fixed))
    switched.REBASE = rebase
    assert switched.usable
    core = np.zeros(src.size, dtype=bool)
    core[switched.links] = True
    for _ in range(8):
        active = fixed | (rng.random(src.size) < rng.uniform(0.3, 1.0))
        found = switched.residuals(active)
        if not _whole_by_count(n, src, dst, active):
            assert found is None  # the full solve holds what is cut off still: not modelled
            continue
        assert found is not None
        distance, turn = _exact_link_residuals(pose, src, dst, transform, active)
        assert found[0] == pytest.approx(distance[core], abs=1e-8)
        assert np.abs(wrap_angle(found[1] - turn[core])).max(initial=0) < 1e-8
        assert distance[~core] == pytest.approx(0.0, abs=1e-8)  # off the 2-core every link fits exactly
        assert np.abs(turn[~core]).max(initial=0.0) < 1e-8


@settings(max_examples=40, deadline=None)
@given(st.one_of(_random_graph(), _laps_graph()), st.integers(0, 2**31 - 1))
def test_the_compiled_run_sums_give_numpys_bits(graph: tuple[np.ndarray, ...], seed: int) -> None:
    """The compiled loops of the low-rank solve (core._switched_kernel) equal their numpy versions bit for bit."""
    from core._switched_kernel import run_sums

    pose, src, dst, transform, fixed = graph
    n = pose.shape[0]
    rng = np.random.default_rng(seed)
    switched = SwitchedRelaxation(pose, src, dst, transform, _anchors(n, src, dst), LinkComponents(n, src, dst, fixed))
    for _ in range(4):
        fields = np.zeros((2, switched.free + 1))
        fields[:, : switched.free] = rng.normal(scale=rng.choice([0.01, 1.0, 30.0]), size=(2, switched.free))
        weight = switched.weight * (rng.random(switched.length.size) < 0.8)
        expected = switched.run_sums_numpy(fields, weight)
        found = run_sums(fields, switched.linear, (switched.local_src, switched.local_dst), switched._link_terms,
                         switched._member_csr, weight, switched._incidence_csr)  # fmt: skip
        for a, b in zip(found, expected, strict=True):
            assert a.tobytes() == b.tobytes()
        runs = switched.switched[0][rng.random(switched.switched[0].size) < 0.5]
        if runs.size == 0:
            continue
        columns = rng.normal(size=(runs.size, switched.free + 1))
        ends = switched.local_src[runs], switched.local_dst[runs]
        update = columns, ends, rng.normal(size=(runs.size, runs.size))
        measured = rng.normal(size=(2, runs.size))
        solved = rng.normal(size=(switched.free, 2))
        links = switched.links
        switched.links = np.zeros(0, np.int64)  # the numpy loops (below COMPILED_FROM links)
        numpy_paths = switched.low_rank(fields, measured, update), switched.low_rank(solved, None, update)
        switched.links = np.zeros(COMPILED_FROM, np.int64)  # the compiled ones
        compiled = switched.low_rank(fields, measured, update), switched.low_rank(solved, None, update)
        switched.links = links
        for a, b in zip(compiled, numpy_paths, strict=True):
            assert a.tobytes() == b.tobytes()


def test_two_anchors_in_one_part_leave_the_low_rank_solve_unused() -> None:
    src, dst = np.array([0, 1, 2]), np.array([1, 2, 0])
    pose = np.zeros((3, 4))
    parts = LinkComponents(3, src, dst, np.zeros(3, dtype=bool))
    one = SwitchedRelaxation(pose, src, dst, np.ones((3, 4)), np.array([True, False, False]), parts)
    two = SwitchedRelaxation(pose, src, dst, np.ones((3, 4)), np.array([True, True, False]), parts)
    assert one.usable and one.residuals(np.ones(3, dtype=bool)) is not None
    assert not two.usable and two.residuals(np.ones(3, dtype=bool)) is None


def test_the_default_settle_ends_on_the_joint_least_squares_with_view_links_weighed_down() -> None:
    """``exp_settle_joint`` with ``exp_loop_weight`` 0.3 (the defaults): settle solves RatSLAM's fixed point, then
    moves the map to Σ w_l²·(‖r_xyz‖² + (h·r_ψ)²) with each loop link's w three tenths of an odometry link's; scipy's
    trust-region least squares finds the same optimum from the fixed point. Without it (must not) the map stays at
    RatSLAM's fixed point."""
    from scipy.optimize import least_squares

    from core.relaxation import length_weights, residuals, solve
    from core.robust import Drift, link_length

    params = Params(exp_initial_em_deg=0.0, exp_loops=10, exp_robust=False)
    assert (params.exp_settle_joint, params.exp_loop_weight) == (True, 0.3)
    em = _square_laps(params)
    before = em.snapshot()
    em.settle()
    src, dst, t, _, distance, kind = (np.asarray(a) for a in em.links)
    start = before["em_pose"].reshape(-1, 4)
    anchor = np.zeros(em.count, dtype=bool)
    anchor[0] = True
    fixed_point = solve(start, src, dst, t, anchor)
    weight = length_weights(distance, link_length(distance, kind)) * np.where(kind == int(LinkKind.LOOP), 0.3, 1.0)
    h = Drift.of(params).heading_weight

    def stacked(free: np.ndarray) -> np.ndarray:
        pose = np.vstack([fixed_point[:1], free.reshape(-1, 4)])
        r = residuals(pose, src, dst, t)
        r[:, 3] *= h
        return (r * weight[:, None]).reshape(-1)

    reference = least_squares(stacked, fixed_point[1:].reshape(-1), xtol=1e-14, ftol=1e-14, gtol=1e-14).x
    assert _pose_error(em.poses[1:], reference.reshape(-1, 4)) < 1e-6
    assert _pose_error(em.poses, fixed_point) > 1e-3  # it moved on from the fixed point
    plain = ExperienceMap.restore(params.replace(exp_settle_joint=False), 3, before)
    plain.settle()
    assert _pose_error(plain.poses, fixed_point) <= TOLERANCE

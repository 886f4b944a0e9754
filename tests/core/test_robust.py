"""Robust relaxation (core.robust): false loop links are switched off, true ones stay on."""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core import pcm, robust
from core._switched_kernel import CompiledScoring
from core.config import Params
from core.experience_map import ExperienceMap, LinkKind
from core.motion import Motion
from core.relaxation import SwitchedRelaxation
from core.robust import (
    Drift,
    _Problem,
    chain_headings,
    component_anchors,
    contradicts_the_map,
    false_loop_links,
    health,
    keep_connected,
    link_length,
    normalised_residuals,
    switch_off_outliers,
    switchable,
)
from tests.core.conftest import departing

DRIFT = Drift(0.1, 0.1, 3.0)
RADIUS = 8.0
STEPS = 40  # experiences per lap, 1.26 m apart


def _circle_graph(laps: int = 2, yaw_bias: float = 0.004, scale: float = 0.98, dz: float = 0.0):
    """Two laps of a circle: true poses, and links measured with odometry drift plus true loop closures.

    Odometry links carry the true relative pose scaled by ``scale`` and turned by ``yaw_bias``
    per link; loop links join experience i of lap 2 to i of lap 1 with the exact relative pose.
    """
    n = laps * STEPS
    angle = 2 * math.pi * np.arange(n) / STEPS
    truth = np.stack([RADIUS * np.cos(angle), RADIUS * np.sin(angle), dz * np.sin(angle), angle + math.pi / 2], 1)
    src = np.arange(n - 1)
    dst = src + 1
    kind = np.zeros(n - 1, dtype=np.int8)
    loop_src = np.arange(STEPS, n, 3)
    loop_dst = loop_src - STEPS
    src = np.concatenate([src, loop_src])
    dst = np.concatenate([dst, loop_dst])
    kind = np.concatenate([kind, np.ones(loop_src.size, dtype=np.int8)])
    transform = _relative(truth[src], truth[dst])
    odometry = kind == 0
    transform[odometry, :3] *= scale
    transform[odometry, 3] += yaw_bias
    distance = np.linalg.norm(transform[:, :3], axis=1)
    return truth, src, dst, transform, kind, distance


def _relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return the pose of ``b`` in the frame of ``a`` (x, y, z, yaw rows)."""
    d = b[:, :3] - a[:, :3]
    c, s = np.cos(a[:, 3]), np.sin(a[:, 3])
    out = np.empty((a.shape[0], 4))
    out[:, 0] = c * d[:, 0] + s * d[:, 1]
    out[:, 1] = -s * d[:, 0] + c * d[:, 1]
    out[:, 2] = d[:, 2]
    out[:, 3] = np.remainder(b[:, 3] - a[:, 3] + math.pi, 2 * math.pi) - math.pi
    return out


def _ape(truth: np.ndarray, pose: np.ndarray) -> float:
    """RMS position error after one rigid alignment (Umeyama without scale, xy plus z offset)."""
    a, b = pose[:, :2] - pose[:, :2].mean(0), truth[:, :2] - truth[:, :2].mean(0)
    u, _, vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(u @ vt))
    rot = u @ np.diag([1.0, d]) @ vt
    err_xy = b - a @ rot.T
    err_z = (truth[:, 2] - truth[:, 2].mean()) - (pose[:, 2] - pose[:, 2].mean())
    return float(np.sqrt(np.mean(np.sum(err_xy**2, 1) + err_z**2)))


def _with_false(graph, count: int, separation: float, seed: int):
    truth, src, dst, transform, kind, distance = graph
    fs, fd, ft = false_loop_links(truth, count, separation, seed)
    return (
        truth,
        np.concatenate([src, fs]),
        np.concatenate([dst, fd]),
        np.concatenate([transform, ft]),
        np.concatenate([kind, np.ones(fs.size, dtype=np.int8)]),
        np.concatenate([distance, np.full(fs.size, 0.1)]),
    ), fs.size


def _run(graph, joint: bool = False):
    truth, src, dst, transform, kind, distance = graph
    start = np.zeros_like(truth)
    start[0] = truth[0]
    anchor = component_anchors(truth.shape[0], src, dst)
    return switch_off_outliers(start, src, dst, transform, kind, distance, anchor, DRIFT, joint=joint)


def test_a_clean_graph_keeps_every_link_and_is_relaxed_once() -> None:
    graph = _circle_graph()
    result = _run(graph)
    assert result.active.all() and result.iterations == 1
    # drift 2 % scale and 0.004 rad per link: each link's residual is a fraction of 0.1·1.26 m
    assert result.z.max() < DRIFT.threshold


@pytest.mark.parametrize(("count", "separation"), [(1, 3.0), (5, 3.0), (10, 3.0), (5, 8.0)])
def test_false_links_are_switched_off_and_the_true_closures_stay(count: int, separation: float) -> None:
    clean = _circle_graph()
    clean_ape = _ape(clean[0], _run(clean).pose)
    graph, injected = _with_false(clean, count, separation, seed=count)
    assert injected == count
    result = _run(graph)
    true_loops = int(np.count_nonzero(clean[4] == 1))
    assert result.active[: clean[1].size].all(), "a true link was switched off"
    assert np.count_nonzero(~result.active[clean[1].size :]) == count
    assert _ape(graph[0], result.pose) <= 1.25 * clean_ape
    # the paired must-still-happen count: all 14 true closures still pull
    assert true_loops == 14 and int(np.count_nonzero(result.active[: clean[1].size] & (clean[4] == 1))) == 14


@pytest.mark.slow
def test_more_wrong_links_than_true_closures_hold_with_the_pairwise_start(monkeypatch: pytest.MonkeyPatch) -> None:
    """20 wrong links against 14 true closures: 9 of 10 seeds keep the clean APE with the pairwise start.

    Measured without it (the greedy descent from all links and from the odometry only, then strained links
    tried off): 7 of 10 (8 before strained links were tried off), the wrong links winning a stretch of the
    loop in 3; that figure is the paired check that the start matters.
    (Accepting the clique start at any lower cost held 10 of 10 here but bent the merged maps of the
    self-aliased ``twin-overlap`` worlds: see core/robust.py.)
    """
    clean = _circle_graph()
    clean_ape = _ape(clean[0], _run(clean).pose)

    def held() -> int:
        count = 0
        for seed in range(10):
            graph, _ = _with_false(clean, 20, 3.0, seed=seed)
            count += _ape(graph[0], _run(graph).pose) <= 1.25 * clean_ape
        return count

    assert held() == 9
    monkeypatch.setattr(robust, "_pairwise_start", lambda *_args: None)
    assert held() == 7


def test_doing_nothing_would_fail_the_apes_bound() -> None:
    """The bound above is not vacuous: with the false links kept the map bends far past it."""
    clean = _circle_graph()
    clean_ape = _ape(clean[0], _run(clean).pose)
    graph, _ = _with_false(clean, 5, 3.0, seed=5)
    truth, src, dst, transform, _, _ = graph
    start = np.zeros_like(truth)
    start[0] = truth[0]
    from core.relaxation import solve

    bent = solve(start, src, dst, transform, component_anchors(truth.shape[0], src, dst))
    assert _ape(truth, bent) > 1.5 * clean_ape


def test_four_dof_false_links_are_switched_off() -> None:
    clean = _circle_graph(dz=0.5)
    graph, _ = _with_false(clean, 5, 3.0, seed=2)
    result = _run(graph)
    assert result.active[: clean[1].size].all()
    assert np.count_nonzero(~result.active) == 5



def _closure_one_place_on(start: int, error: float):
    """The circle graph plus a closure from lap 2's experience ``STEPS + start`` to lap 1's ``start``.

    Its transform is the true relative pose with ``error`` metres added along the source's x: a
    closure to the right place measured ``error`` m off, like the wrong links of ``cave3d`` (0.85 m).
    """
    truth, src, dst, transform, kind, distance = _circle_graph()
    a, b = STEPS + start, start
    wrong = _relative(truth[[a]], truth[[b]])[0] + np.array([error, 0.0, 0.0, 0.0])
    return (truth, np.append(src, a), np.append(dst, b), np.vstack([transform, wrong]), np.append(kind, 1),
            np.append(distance, 0.05))  # fmt: skip


@pytest.mark.parametrize(("start", "error"), [(5, 0.8), (21, 0.6)])
def test_a_wrong_link_within_the_threshold_is_switched_off_when_the_cost_falls(
    start: int, error: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A link 0.6-0.8 m off bends the graph until its own z is 2.3-2.8 < c̄ = 3: the descent keeps it.

    Trying it off lowers the TLS cost, so it goes; every true closure stays on; the APE is the clean
    graph's. Without the step (monkeypatched away) it stays on: the paired must-fail.
    """
    graph = _closure_one_place_on(start, error)
    clean_ape = _ape(graph[0], _run(_circle_graph()).pose)
    k = graph[1].size - 1
    result = _run(graph)
    assert not result.active[k] and result.active[:k].all()
    assert _ape(graph[0], result.pose) == pytest.approx(clean_ape, rel=1e-6)
    monkeypatch.setattr(robust._Problem, "switch_off_strained", lambda _self, best: best)
    kept = _run(graph)
    assert kept.active.all() and DRIFT.threshold / 2 < kept.z[k] < DRIFT.threshold
    assert _ape(graph[0], kept.pose) > 1.015 * clean_ape  # measured 1.045 and 1.020


def test_a_relocalisations_odometry_link_is_not_tried_off_for_strain() -> None:
    """The same strained link as a relocalisation's odometry link (odometry kind, switchable) is not tried.

    Off, its reckoning link would stand in: the robot's odometry over what may be tens of metres
    (``twin-overlap`` 40 m seed 5: merged APE 0.95 → 1.71 m when these were tried). As a loop link it goes.
    """
    truth, src, dst, transform, kind, distance = _closure_one_place_on(5, 0.8)
    start = np.zeros_like(truth)
    start[0] = truth[0]
    anchor = component_anchors(truth.shape[0], src, dst)
    as_odometry = kind.copy()
    as_odometry[-1] = 0
    relocalised = np.zeros(src.size, dtype=bool)
    relocalised[-1] = True
    kept = switch_off_outliers(start, src, dst, transform, as_odometry, distance, anchor, DRIFT,
                               also_switchable=relocalised)  # fmt: skip
    assert kept.active.all() and DRIFT.threshold / 2 < kept.z[-1] < DRIFT.threshold
    loop = switch_off_outliers(start, src, dst, transform, kind, distance, anchor, DRIFT)
    assert not loop.active[-1] and loop.active[:-1].all()


@pytest.mark.parametrize("error", [0.2, 0.4])
def test_a_closure_measured_a_little_off_stays_on(error: float) -> None:
    """The must-still-happen side: closures 0.2-0.4 m off (z 0.6-1.8) are within what the cost forgives."""
    graph = _closure_one_place_on(5, error)
    result = _run(graph)
    assert result.active.all()

@settings(max_examples=15, deadline=None)
@given(st.floats(-50, 50), st.floats(-50, 50), st.floats(-3, 3), st.floats(-math.pi, math.pi), st.integers(0, 3))
def test_a_consistent_graph_keeps_all_links_under_any_rigid_motion(
    tx: float, ty: float, tz: float, turn: float, seed: int
) -> None:
    graph = _circle_graph(yaw_bias=0.002 * seed, scale=1.0 - 0.01 * seed)
    truth, src, dst, transform, kind, distance = graph
    c, s = math.cos(turn), math.sin(turn)
    moved = truth.copy()
    moved[:, 0] = c * truth[:, 0] - s * truth[:, 1] + tx
    moved[:, 1] = s * truth[:, 0] + c * truth[:, 1] + ty
    moved[:, 2] += tz
    moved[:, 3] = np.remainder(truth[:, 3] + turn + math.pi, 2 * math.pi) - math.pi
    anchor = component_anchors(truth.shape[0], src, dst)
    result = switch_off_outliers(moved, src, dst, transform, kind, distance, anchor, DRIFT)
    assert result.active.all()


def test_chain_headings_dead_reckon_along_odometry_unwrapped() -> None:
    src = np.array([0, 1, 2, 3, 0])
    dst = np.array([1, 2, 3, 4, 4])
    transform = np.zeros((5, 4))
    transform[:4, 3] = 2.0  # four turns of 2 rad: 8 rad in all, past 2π
    transform[4, 3] = 1.0  # a loop link that would say 1 rad
    avoid = np.array([False, False, False, False, True])
    anchor = np.array([True, False, False, False, False])
    yaw = chain_headings(np.full(5, 0.5), src, dst, transform, avoid, anchor)
    assert yaw.tolist() == pytest.approx([0.5, 2.5, 4.5, 6.5, 8.5])


def test_keep_connected_turns_a_bridge_back_on_lowest_residual_first() -> None:
    # 0-1-2 path, and two links joining 2 and 3 (both switched off): one of them must come back
    src = np.array([0, 1, 2, 3])
    dst = np.array([1, 2, 3, 2])
    active = np.array([True, True, False, False])
    z = np.array([0.0, 0.0, 9.0, 4.0])
    assert keep_connected(4, src, dst, active, z).tolist() == [True, True, False, True]
    assert keep_connected(4, src, dst, np.ones(4, dtype=bool), z).all()


def test_health_is_the_rms_of_normalised_residuals_of_active_links() -> None:
    pose = np.array([[0.0, 0, 0, 0], [1.0, 0, 0, 0], [2.0, 0.2, 0, 0]])
    src, dst = np.array([0, 1, 0]), np.array([1, 2, 2])
    transform = np.array([[1.0, 0, 0, 0], [1.0, 0, 0, 0], [0.0, 0, 0, 0]])
    kind = np.array([0, 0, 1])
    distance = np.array([1.0, 1.0, 0.0])
    # link 1: residual 0.2 m over drift 0.1·1 m → z = 2; link 0: 0; link 2 (off): ignored
    h = health(pose, src, dst, transform, kind, distance, np.array([True, True, False]), DRIFT)
    assert h == {"residual": pytest.approx(math.sqrt(2)), "worst": pytest.approx(2.0), "switched_off": 1, "links": 3,
                 "unmeasured": 0}  # fmt: skip
    z = normalised_residuals(pose, src, dst, transform, 1.0, DRIFT)
    assert z[:2].tolist() == pytest.approx([0.0, 2.0])


@pytest.mark.parametrize("bad", [math.inf, -math.inf])
def test_an_infinite_link_is_counted_unmeasured_and_the_figure_stays_finite(bad: float) -> None:
    """A stored transform holding an infinity has no residual: counted apart, the others' figure unchanged."""
    pose = np.array([[0.0, 0, 0, 0], [1.0, 0, 0, 0], [2.0, 0.2, 0, 0]])
    src, dst = np.array([0, 1, 0]), np.array([1, 2, 2])
    transform = np.array([[1.0, 0, 0, 0], [1.0, 0, 0, 0], [bad, 0, 0, 0]])
    kind, distance = np.array([0, 0, 1]), np.array([1.0, 1.0, 0.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning escapes
        h = health(pose, src, dst, transform, kind, distance, np.ones(3, dtype=bool), DRIFT)
    # the two finite links as in the test above (z 0 and 2); the infinite one apart
    assert h == {"residual": pytest.approx(math.sqrt(2)), "worst": pytest.approx(2.0), "switched_off": 0, "links": 3,
                 "unmeasured": 1}  # fmt: skip
    assert json.loads(json.dumps(h, allow_nan=False)) == h


def test_false_loop_links_are_deterministic_and_far_apart() -> None:
    truth = _circle_graph()[0]
    a = false_loop_links(truth, 5, 4.0, seed=7)
    b = false_loop_links(truth, 5, 4.0, seed=7)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    gap = np.linalg.norm(truth[a[0], :3] - truth[a[1], :3], axis=1)
    assert np.all((gap >= 4.0) & (gap <= 6.0)) and np.all(np.linalg.norm(a[2][:, :2], axis=1) <= 0.2)


def _pose_gap(a: np.ndarray, b: np.ndarray) -> float:
    """Return the largest difference of two pose arrays (headings compared modulo 2π)."""
    turn = np.abs(np.remainder(a[:, 3] - b[:, 3] + math.pi, 2 * math.pi) - math.pi)
    return float(max(np.abs(a[:, :3] - b[:, :3]).max(), turn.max()))


def _lap_map(params: Params) -> ExperienceMap:
    """An experience map driven twice around a 16-gon with exact loop closures on lap 2."""
    em = ExperienceMap(params, 3)
    em.create_experience(0, np.zeros(3), 0.0, 0)
    for i in range(1, 32):
        em.on_odo(Motion(1.0, 0.0, 0.0, 2 * math.pi / 16 + 0.003, 1.0))
        if i < 16:
            em.create_experience(i, np.zeros(3), float(i), 0)
        else:
            em.create_link(em.current, i - 16, 0.0, LinkKind.LOOP)
            em.set_experience(i - 16, 0.0)
        em.relax_step()
    return em


def test_experience_map_switches_a_false_link_off_and_keeps_it_in_the_snapshot() -> None:
    params = departing()
    em = _lap_map(params)
    em.settle()
    assert em.link_active.all()
    clean = em.poses.copy()
    assert em.add_link_raw(3, 11, np.array([0.1, 0.0, 0.0, 0.0]), 1.0, 0.1, LinkKind.LOOP)
    em.settle()
    assert em.link_active.tolist() == [True] * (em.link_count - 1) + [False]
    assert _pose_gap(em.poses, clean) < 1e-6  # the false link no longer pulls
    state = em.snapshot()
    assert state["em_link_active"].tolist() == em.link_active.tolist()
    again = ExperienceMap.restore(params, 3, state)
    assert again.link_active.tolist() == em.link_active.tolist()
    assert all(np.array_equal(v, again.snapshot()[k]) for k, v in state.items())


def test_experience_map_without_robust_check_keeps_the_false_link() -> None:
    params = departing(exp_robust=False)
    em = _lap_map(params)
    em.settle()
    clean = em.poses.copy()
    em.add_link_raw(3, 11, np.array([0.1, 0.0, 0.0, 0.0]), 1.0, 0.1, LinkKind.LOOP)
    em.settle()
    assert em.link_active.all() and _pose_gap(em.poses, clean) > 0.5


def test_the_check_is_deterministic_bit_for_bit() -> None:
    graph, _ = _with_false(_circle_graph(), 5, 3.0, seed=3)
    a, b = _run(graph), _run(graph)
    assert np.array_equal(a.active, b.active) and np.array_equal(a.pose, b.pose) and np.array_equal(a.z, b.z)
    maps = []
    for _ in range(2):
        em = _lap_map(departing())
        em.add_link_raw(3, 11, np.array([0.1, 0.0, 0.0, 0.0]), 1.0, 0.1, LinkKind.LOOP)
        em.settle()
        maps.append(em.snapshot())
    assert all(np.array_equal(v, maps[1][k]) for k, v in maps[0].items())


@pytest.mark.parametrize("count", [3, 8])
def test_false_links_that_agree_with_one_another_are_switched_off_though_none_stands_out(count: int) -> None:
    """A look-alike place closed again and again: ``count`` false links, each saying "node i is node i + 20"
    (the opposite side of one lap, 16 m away), fold the lap until none of them exceeds c̄, so the greedy
    elimination alone keeps them all; the descent started from the odometry alone switches every one off.
    With a yaw drift of 0.03 rad/m: at the default 0.1 rad/m folding the half lap costs less than c̄² (a
    known limit, docs/journal.md, "folds")."""
    truth, src, dst, transform, kind, distance = _circle_graph(laps=1)
    near = np.arange(2, 2 + count)
    graph = (truth, np.concatenate([src, near]), np.concatenate([dst, near + STEPS // 2]),
             np.concatenate([transform, np.zeros((count, 4))]), np.concatenate([kind, np.ones(count, dtype=np.int8)]),
             np.concatenate([distance, np.zeros(count)]))  # fmt: skip
    drift = Drift(0.1, 0.03, 3.0)
    start = np.zeros_like(truth)
    start[0] = truth[0]
    anchor = component_anchors(truth.shape[0], graph[1], graph[2])
    result = switch_off_outliers(start, *graph[1:], anchor, drift)
    assert not result.active[src.size :].any() and result.active[: src.size].all()
    assert _ape(truth, result.pose) < 0.6
    # the paired must-fail: the greedy elimination from all links on keeps every false link (APE > 7 m)
    can = switchable(graph[4])
    headings = start.copy()
    headings[:, 3] = chain_headings(start[:, 3], graph[1], graph[2], graph[3], can, anchor)
    problem = _Problem(headings, graph[1], graph[2], graph[3], can, anchor, link_length(graph[5], graph[4]), drift, 400)
    greedy = problem.eliminate(np.ones(graph[1].size, dtype=bool))
    assert greedy.active[src.size :].all() and _ape(truth, greedy.pose) > 7.0


def _fold_map(params: Params, false: bool) -> tuple[ExperienceMap, np.ndarray]:
    """One lap of a 16-gon (1 m sides), then a relocalisation and 8 new experiences along the true lap 2.

    ``false``: the robot, back at vertex 0, relocalises onto experience 8 (the opposite vertex, 5.1 m
    away, heading turned by π): the new experiences hang off 8 and fold onto the far side. Otherwise it
    relocalises onto 0, where it is. Returns the map and the true positions of its experiences.
    """
    em = ExperienceMap(params, 3)
    em.create_experience(0, np.zeros(3), 0.0, 0)
    step = Motion(1.0, 0.0, 0.0, 2 * math.pi / 16 + 0.003, 1.0)
    for i in range(1, 16):
        em.on_odo(step)
        em.create_experience(i, np.zeros(3), float(i), 0)
    em.on_odo(step)
    target = 8 if false else 0
    em.create_link(em.current, target, 0.0, LinkKind.LOOP)
    em.set_experience(target, 0.0)
    for j in range(1, 9):
        em.on_odo(step)
        em.create_experience(15 + j, np.zeros(3), 15.0 + j, 0)
    radius = 0.5 / math.sin(math.pi / 16)
    vertex = np.r_[np.arange(16), np.arange(1, 9)] * 2 * math.pi / 16
    truth = np.stack([radius * np.sin(vertex), radius * (1 - np.cos(vertex)), np.zeros(24), vertex], 1)
    return em, truth


def test_a_false_relocalisation_is_unfolded_by_the_robots_own_odometry() -> None:
    em, truth = _fold_map(departing(), false=True)
    links = em.link_count
    em.settle()
    src, dst, _, _, _, kind = em.links
    assert not em.link_active[15] and not em.link_active[16]  # the closure 15 → 8 and the odometry 8 → 16 it made
    assert em.link_count == links + 1 and (int(src[-1]), int(dst[-1]), int(kind[-1])) == (15, 16, 0)
    assert _ape(truth, em.poses) < 0.1  # the yaw bias of 0.003 rad per step alone
    # the paired must-fail: the same map without its reckoning link keeps the fold (the closure alone goes off)
    state = em.snapshot()
    folded, _ = _fold_map(departing(), false=True)
    bare = folded.snapshot()
    for key in ("em_reckon_from", "em_reckon_to", "em_reckon_link"):
        bare.pop(key)
    folded = ExperienceMap.restore(departing(), 3, bare)
    folded.settle()
    assert folded.link_count == links and _ape(truth, folded.poses) > 1.5
    assert state["em_link_active"].size == links + 1


def test_a_true_relocalisation_keeps_its_closure_and_odometry_and_adds_nothing() -> None:
    em, truth = _fold_map(departing(), false=False)
    links = em.link_count
    em.settle()
    assert em.link_active.all() and em.link_count == links
    assert _ape(truth, em.poses) < 0.1  # the yaw bias of 0.003 rad per step alone


def _closed_lap(sides: int, step: Motion) -> ExperienceMap:
    """A lap of ``sides`` experiences (0..sides−1), one ``step`` apart, closed by a loop link back onto 0 (current)."""
    em = ExperienceMap(departing(), 3)
    em.create_experience(0, np.zeros(3), 0.0, 0)
    for i in range(1, sides):
        em.on_odo(step)
        em.create_experience(i, np.zeros(3), float(i), 0)
    em.on_odo(step)
    em.create_link(em.current, 0, 0.0, LinkKind.LOOP)
    em.set_experience(0, 0.0)
    return em


def _twice_relocalised_map(first_false: bool, short: float = 0.0) -> tuple[ExperienceMap, np.ndarray]:
    """A 16-gon lap (0-15) closed onto 0, then 7 new experiences along vertices 1-7 (16-22, yaw bias 0.02 rad
    per step); at vertex 8 the robot closes onto 0 (``first_false``: the far side, 5.1 m away) or onto 8, moves
    on along links that exist to 9 without a new link (as the engine does when the link is there), and makes 23-25
    at vertices 10-12 from 9. After the lap the odometry reads ``short`` too little. Returns the map and the
    true positions of its experiences."""
    em = _closed_lap(16, Motion(1.0, 0.0, 0.0, 2 * math.pi / 16 + 0.02, 1.0))
    step = Motion(1.0 - short, 0.0, 0.0, 2 * math.pi / 16 + 0.02, 1.0)
    for j in range(1, 8):
        em.on_odo(step)
        em.create_experience(15 + j, np.zeros(3), 15.0 + j, 0)
    em.on_odo(step)
    target = 0 if first_false else 8
    em.create_link(em.current, target, 0.0, LinkKind.LOOP)
    em.set_experience(target, 0.0)
    em.on_odo(step)
    em.set_experience(9, 0.0)
    for j in range(3):
        em.on_odo(step)
        em.create_experience(23 + j, np.zeros(3), 25.0 + j, 0)
    radius = 0.5 / math.sin(math.pi / 16)
    vertex = np.r_[np.arange(16), np.arange(1, 8), np.arange(10, 13)] * 2 * math.pi / 16
    truth = np.stack([radius * np.sin(vertex), radius * (1 - np.cos(vertex)), np.zeros(26), vertex], 1)
    return em, truth


def test_a_false_closure_before_a_true_relocalisation_lets_the_robots_odometry_join_what_it_left(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The false closure 22 → 0 goes off; the robot's next experience hangs off 9 by a true link, so the
    reckoning link 22 → 23 is the only thing joining 16-22 to the lap at their far end: it joins the map."""
    em, truth = _twice_relocalised_map(first_false=True)
    links = em.link_count
    em.settle()
    src, dst, _, _, _, kind = em.links
    assert em.link_count == links + 1 and (int(src[-1]), int(dst[-1]), int(kind[-1])) == (22, 23, 0)
    assert np.array_equal(np.flatnonzero(~em.link_active), [23])  # only the false closure is off
    joined = _ape(truth, em.poses)
    assert joined < 0.06  # the yaw bias of 0.02 rad per step alone
    # the paired must-fail: without the closure rule the reckoning link stands by while 9 → 23 stands, so the
    # check switches off the true lap closure 15 → 0 and 9 → 23 as well to let it in (APE 0.21 m). The status
    # quo's start, tried when the answer switches off a link that stood, keeps the lap closure on by itself
    # (only 22 → 0 off, APE 0.09 m), so it is patched out too: the case of a map with no previous check.
    monkeypatch.setattr("core.experience_map._last_loop_from", lambda src, kind, start, before: np.full(start.size, -1))
    monkeypatch.setattr("core.robust._status_quo_start", lambda _problem, _status_quo: None)
    hanging, _ = _twice_relocalised_map(first_false=True)
    hanging.settle()
    assert not hanging.link_active[15] and _ape(truth, hanging.poses) > 3 * joined


@pytest.mark.parametrize(("short", "kept"), [(0.1, True), (0.3, True), (0.4, True), (0.5, True), (0.7, False)])
def test_where_the_closure_rule_stops_keeping_a_true_relocalisation(
    short: float, kept: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The same double relocalisation with the second pass's odometry ``short`` too little: the reckoning link 22 → 23
    joins and the map beats the rule patched out (APE 0.16/0.44/0.58 m against 0.23/0.57/0.91 m at 10, 30, 40 %) while
    the true relocalisation 9 → 23 stays on; at 50 % short too, where the lap closure 15 → 0 goes off instead (0.71 m
    against 1.11: the cheaper answer, which the status quo's start finds; the other switches 9 → 23 off, 1.11 m); at
    70 % short 9 → 23 is switched off, with or without the rule (1.50 m both): where it breaks."""
    em, truth = _twice_relocalised_map(first_false=True, short=short)
    em.settle()
    assert not em.link_active[23] and bool(em.link_active[24]) is kept
    with_rule = _ape(truth, em.poses)
    monkeypatch.setattr("core.experience_map._last_loop_from", lambda src, kind, start, before: np.full(start.size, -1))
    without, _ = _twice_relocalised_map(first_false=True, short=short)
    without.settle()
    if kept:
        assert with_rule < 0.85 * _ape(truth, without.poses)
    else:
        assert with_rule == pytest.approx(_ape(truth, without.poses))


def test_a_true_closure_before_a_relocalisation_adds_nothing() -> None:
    em, truth = _twice_relocalised_map(first_false=False)
    links = em.link_count
    em.settle()
    assert em.link_active.all() and em.link_count == links
    assert _ape(truth, em.poses) < 0.06  # the yaw bias of 0.02 rad per step alone


def _two_sessions(false: bool, merged: bool = True):
    """Session A: a 32-gon (1 m sides, ids 0-31); session B: 8 experiences along A's vertices 1-8 (ids 32-39)
    joined to A by a merge link 32 → 1. Loop links from B's 36-39: onto A's 5-8 (true) or, ``false``, onto the
    opposite vertices 21-24 (10.2 m away, turned by π) with the transform of a true closure; the four false
    ones agree with one another (B's stretch turned rigidly onto A's far side)."""
    sides = 32
    radius = 0.5 / math.sin(math.pi / sides)
    vertex = np.r_[np.arange(sides), np.arange(1, 9)] * 2 * math.pi / sides
    truth = np.stack([radius * np.sin(vertex), radius * (1 - np.cos(vertex)), np.zeros(40), vertex], 1)
    src = np.r_[np.arange(31), np.arange(32, 39)]
    dst = src + 1
    kind = np.zeros(src.size, dtype=np.int8)
    closures = np.arange(36, 40)
    targets = closures - 31 + (16 if false else 0)
    if merged:
        src, dst, kind = np.r_[src, 32], np.r_[dst, 1], np.r_[kind, 2].astype(np.int8)
    transform = _relative(truth[src], truth[dst])
    transform[kind == 0, 3] += 0.003  # odometry yaw bias
    loop_t = _relative(truth[closures], truth[closures - 31])  # what a true closure measures
    src, dst = np.r_[src, closures], np.r_[dst, targets]
    kind = np.r_[kind, np.ones(4, dtype=np.int8)]
    transform = np.concatenate([transform, loop_t])
    distance = np.linalg.norm(transform[:, :3], axis=1)
    return truth, src, dst, transform, kind, distance


@pytest.mark.parametrize("false", [True, False])
def test_links_that_contradict_their_sessions_odometry_are_switched_off_though_they_agree(false: bool) -> None:
    """B's experiences continue A's session by odometry (32 → 1 an odometry link): the four false closures
    agree with one another, and each contradicts the odometry of the route between its own ends."""
    truth, src, dst, transform, kind, distance = _two_sessions(false)
    kind = np.where(kind == 2, 0, kind).astype(np.int8)
    anchor = component_anchors(truth.shape[0], src, dst)
    result = switch_off_outliers(np.zeros_like(truth), src, dst, transform, kind, distance, anchor, DRIFT)
    assert result.active[kind != 1].all()
    assert not result.active[kind == 1].any() if false else result.active[kind == 1].all()
    assert _ape(truth, result.pose) < 0.2  # the odometry's yaw bias (0.003 rad per link) alone: 0.14 m


def test_links_the_odometry_does_not_join_are_gated_by_their_turn_only() -> None:
    """Across sessions joined by a merge link the cycle carries the merge's own error (a metre at the map
    origin, more along a lever arm), which flagged true closures of ``twin-overlap``: there only the heading
    is tested (docs/journal.md, "folds across sessions"). The four false closures turn their cycle by π: flagged."""
    truth, src, dst, transform, kind, distance = _two_sessions(True)
    length = link_length(distance, kind)
    merge = kind == 2
    assert not robust.contradicts_odometry(truth, src, dst, transform, distance, switchable(kind), length, DRIFT).any()
    flagged = robust.contradicts_odometry(truth, src, dst, transform, distance, switchable(kind), length, DRIFT,
                                          bridge=merge)  # fmt: skip
    assert flagged.tolist() == (kind == 1).tolist()
    # the paired must-flag: the same links, B joined to A by odometry (the one-link z test)
    one = np.where(kind == 2, 0, kind).astype(np.int8)
    flagged = robust.contradicts_odometry(truth, src, dst, transform, distance, switchable(one), length, DRIFT)
    assert flagged.tolist() == (one == 1).tolist()


def test_true_closures_across_a_merge_are_not_gated_whatever_their_translation() -> None:
    """The must-not-flag pair: true closures across the merge link, with the merge link 3 m off (its error
    at the map origin); and false closures that only shift (two vertices on, turned 0.39 rad) stay to the
    TLS cost: the heading test flags turns, not translations."""
    truth, src, dst, transform, kind, distance = _two_sessions(False)
    merge = kind == 2
    transform[merge, 0] += 3.0
    length = link_length(distance, kind)
    args = (switchable(kind), length, DRIFT)
    assert not robust.contradicts_odometry(truth, src, dst, transform, distance, *args, bridge=merge).any()
    dst = np.where(kind == 1, dst + 2, dst)
    assert not robust.contradicts_odometry(truth, src, dst, transform, distance, *args, bridge=merge).any()


@pytest.mark.parametrize("false", [True, False])
def test_a_fold_across_a_merge_is_switched_off_and_true_closures_kept(false: bool) -> None:
    """symmetric seed 0's failure in small: session B, merged into A, closes onto A's far side turned by π."""
    truth, src, dst, transform, kind, distance = _two_sessions(false)
    anchor = component_anchors(truth.shape[0], src, dst)
    result = switch_off_outliers(np.zeros_like(truth), src, dst, transform, kind, distance, anchor, DRIFT)
    assert result.active[kind != 1].all()
    assert not result.active[kind == 1].any() if false else result.active[kind == 1].all()
    assert _ape(truth, result.pose) < 0.2


def _hairpin(yaw_bias: float):
    """40 m east, a 3 m-radius U-turn, 40 m back west; odometry turned by ``yaw_bias`` per link; one true
    closure from the last experience to the first (6 m apart)."""
    yaw = np.r_[np.zeros(40), np.linspace(0, math.pi, 11)[1:], np.full(40, math.pi)]
    step = np.ones(yaw.size)
    step[40:50] = 3 * math.pi / 10
    xy = np.cumsum(np.stack([step * np.cos(yaw), step * np.sin(yaw)], 1), 0)
    truth = np.column_stack([xy, np.zeros(yaw.size), yaw])
    n = yaw.size
    src, dst = np.r_[np.arange(n - 1), n - 1], np.r_[np.arange(1, n), 0]
    kind = np.r_[np.zeros(n - 1, np.int8), np.ones(1, np.int8)]
    transform = _relative(truth[src], truth[dst])
    transform[kind == 0, 3] += yaw_bias
    return truth, src, dst, transform, kind, np.linalg.norm(transform[:, :3], axis=1)


@pytest.mark.parametrize("yaw_bias", [0.01, 0.02])
def test_a_true_closure_after_heading_drift_is_not_gated(yaw_bias: float, monkeypatch: pytest.MonkeyPatch) -> None:
    """The odometry turned 0.9 or 1.8 rad too far over the 91 m hairpin, so its far leg swung by metres: the
    closure's translation misses by more than drift·L, explained by the heading misclosure times a lever arm
    (``twin`` with 40 m look-alikes holding turns: session 2 alone 1.47 m, 10.64 m when this was gated). The
    must-fail pair: without the heading term of the allowance the same closure is flagged."""
    truth, src, dst, transform, kind, distance = _hairpin(yaw_bias)
    args = (truth, src, dst, transform, distance, switchable(kind), link_length(distance, kind), DRIFT)
    assert not robust.contradicts_odometry(*args).any()
    monkeypatch.setattr(pcm, "BRIDGED_TURN", -math.inf)  # no turn is one the odometry explains
    assert robust.contradicts_odometry(*args).tolist() == (kind == 1).tolist()


def test_a_closure_turned_beyond_the_odometrys_heading_drift_is_still_gated() -> None:
    """Where it breaks: 2.7 rad of heading drift over 91 m is more than 0.8 rad + 0.015 rad/m allows, so the
    true closure looks like a mirror place's and is flagged."""
    truth, src, dst, transform, kind, distance = _hairpin(0.03)
    args = (truth, src, dst, transform, distance, switchable(kind), link_length(distance, kind), DRIFT)
    assert robust.contradicts_odometry(*args).tolist() == (kind == 1).tolist()


def _step_back_map(heading_error: float, gap: float = 0.5) -> tuple[ExperienceMap, np.ndarray]:
    """A straight route of 1 m steps (experiences 0-12), a false relocalisation, then 13-25 and a second pass.

    0.5 m past experience 12 the robot relocalises onto 11 (linked to 12 already, so no loop link: a step
    back, as RatSLAM makes when a recent template matches again), and experience 13 hangs off 11 by 0.5 m
    where it lies 2 m ahead (``twin-overlap`` 40 m seed 6: 0.5 m claimed, 3.6 m true). A second pass links
    12 → 13 by 1 m, its heading ``heading_error`` off: 11 → 13 and that loop link contradict each other, and
    the reckoning link 12 → 13 (1 m, the robot's own odometry) says which is right. ``gap``: metres driven
    from the relocalisation to experience 13 (0.5 above).
    """
    em = ExperienceMap(departing(), 3)
    em.create_experience(0, np.zeros(3), 0.0, 0)
    step = Motion(1.0, 0.0, 0.0, 0.002, 1.0)
    for i in range(1, 13):
        em.on_odo(step)
        em.create_experience(i, np.zeros(3), float(i), 0)
    half = Motion(0.5, 0.0, 0.0, 0.0, 0.5)
    em.on_odo(half)
    assert not em.create_link(em.current, 11, 0.0, LinkKind.LOOP)  # 11 → 12 exists: no closure link
    em.set_experience(11, 0.0)
    em.on_odo(Motion(gap, 0.0, 0.0, 0.0, 0.5))
    em.create_experience(13, np.zeros(3), 13.0, 0)
    for i in range(14, 26):
        em.on_odo(step)
        em.create_experience(i, np.zeros(3), float(i), 0)
    em.set_experience(12, 0.0)
    em.on_odo(Motion(0.5 + gap, 0.0, 0.0, heading_error, 1.0))
    assert em.create_link(12, 13, 0.0, LinkKind.LOOP)
    x = np.r_[np.arange(13.0), 12.5 + gap + np.arange(13.0)]
    truth = np.stack([x, np.zeros(26), np.zeros(26), np.zeros(26)], 1)
    return em, truth


@pytest.mark.parametrize("heading_error", [0.0, 0.3])
def test_a_relocalisation_beyond_the_robots_own_reach_is_undone(
    heading_error: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    """11 → 13 puts the robot 2 m from where its 1 m of odometry says: its reckoning link, left out, counts as
    an outlier (``_Problem.overreached``), so undoing the relocalisation is the cheaper answer whether the
    contradicting loop link is kept (0 rad) or gated (0.3 rad off): 11 → 13 goes off, the reckoning link joins.
    The paired must-fail: uncounted, the two answers tie (or keeping wins) and the fold stays (APE > 0.4 m)."""
    em, truth = _step_back_map(heading_error)
    em.settle()
    src, dst, _, _, _, kind = em.links
    relocalised = int(np.flatnonzero((src == 11) & (dst == 13))[0])
    assert not em.link_active[relocalised]
    assert (int(src[-1]), int(dst[-1]), int(kind[-1])) == (12, 13, int(LinkKind.ODOMETRY))
    assert _ape(truth, em.poses) < 0.1
    monkeypatch.setattr(robust._Problem, "overreached", lambda _self, _active, _z: 0)
    folded, _ = _step_back_map(heading_error)
    folded.settle()
    assert folded.link_active[relocalised] and _ape(truth, folded.poses) > 0.4


@pytest.mark.parametrize(("gap", "undone"), [(0.5, True), (1.0, True), (2.0, False), (3.0, False)])
def test_where_the_reach_rule_stops_undoing_a_false_relocalisation(gap: float, undone: bool) -> None:
    """The sweep of the rule's strength: the relocalisation puts the robot 1.5 m off; the contradicting loop link
    is gated (0.3 rad off), so the reckoning link alone decides. It is undone while the robot drove less than
    that (0.5 + ``gap`` ≤ 1.5 m) to its next experience, and kept beyond, where its odometry could have gone
    that far (measured: APE 0.05-0.33 m undone, 0.75 m kept)."""
    em, truth = _step_back_map(0.3, gap)
    em.settle()
    src, dst, _, _, _, _ = em.links
    relocalised = int(np.flatnonzero((src == 11) & (dst == 13))[0])
    assert em.link_active[relocalised] != undone
    assert (_ape(truth, em.poses) < 0.4) == undone


@pytest.mark.parametrize(
    ("short", "turn", "kept"), [(0.05, 0.005, True), (0.6, 0.05, True), (0.0, 0.4, True), (0.7, 0.06, False)]
)
def test_a_true_relocalisation_after_a_long_drifting_ride_keeps_everything(
    short: float, turn: float, kept: bool
) -> None:
    """The must-still-happen side: a lap of a 32-gon closed onto experience 0, 28 m of relocalised driving on
    the first lap with odometry ``short`` (fraction) short and turning ``turn`` rad/m more, then experience 32.
    The reckoning link misses the map by less than its own length: nothing counts, every link stays on, nothing
    joins — up to 60 % short (or 0.4 rad/m of turn alone, the simulator's odometry is 2.5 % and 0.004 rad/m);
    at 70 % short the reckoning link overreaches and the true relocalisation is undone: where it breaks."""
    em = _closed_lap(32, Motion(1.0, 0.0, 0.0, 2 * math.pi / 32, 1.0))
    ride = Motion(1.0 - short, 0.0, 0.0, 2 * math.pi / 32 + turn, 1.0)
    for j in range(1, 28):
        em.on_odo(ride)
        em.set_experience(j, 0.0)
    em.on_odo(ride)
    em.create_experience(32, np.zeros(3), 32.0, 0)
    links = em.link_count
    em.settle()
    assert (em.link_active.all() and em.link_count == links) == kept


def test_last_loop_from_by_hand() -> None:
    """Loop links (kind 1) are indices 1 (from 1), 2 and 5 (from 5), 4 (from 2), 6 (from 9); per (start,
    before): the last loop leaving ``start`` with an index below ``before``, else −1."""
    from core.experience_map import _last_loop_from

    src = np.array([0, 1, 5, 5, 2, 5, 9])
    kind = np.array([0, 1, 1, 0, 1, 1, 1], dtype=np.int8)
    start = np.array([5, 5, 5, 2, 7, 0, 1, 1])
    before = np.array([2, 3, 6, 3, 9, 9, 0, 2])
    assert _last_loop_from(src, kind, start, before).tolist() == [-1, 2, 5, -1, -1, -1, -1, 1]
    assert _last_loop_from(src, np.zeros(7, dtype=np.int8), start, before).tolist() == [-1] * 8


def _turned_closure_lap(joint: bool) -> float:
    """Settle a 32-gon lap of 1.5 m sides closed onto 0 by a link turned 0.2 rad; return its APE (all links on)."""
    em = ExperienceMap(departing().replace(exp_relax_joint=joint), 3)
    em.create_experience(0, np.zeros(3), 0.0, 0)
    step = Motion(1.5, 0.0, 0.0, 2 * math.pi / 32, 1.0)
    for i in range(1, 32):
        em.on_odo(step)
        em.create_experience(i, np.zeros(3), float(i), 0)
    em.on_odo(step)
    em.create_link(em.current, 0, 0.2, LinkKind.LOOP)
    em.settle()
    assert em.link_active.all()
    corner = np.arange(32) * 2 * math.pi / 32
    truth = np.cumsum(1.5 * np.column_stack([np.cos(corner), np.sin(corner)]), axis=0)
    return _ape(np.column_stack([np.vstack([[0.0, 0.0], truth[:-1]]), np.zeros(32)]), em.poses)


def test_a_closure_turned_by_its_view_settles_closer_to_the_truth_jointly() -> None:
    """A lap closed by a link whose heading is 0.2 rad off (a forward view matched a little round, its
    translation right): RatSLAM's fixed point takes the turn into the headings alone, and the lap misses in
    position by it times its lever arm (APE 0.19 m); with ``exp_relax_joint`` the settled map is the joint least
    squares, which shares it between positions and headings (0.14 m; the optimum itself is checked against
    scipy in ``test_relaxation``). Least squares cannot tell the closure's heading from the odometry's, so a
    part of the error stays."""
    decoupled, joint = _turned_closure_lap(False), _turned_closure_lap(True)
    assert decoupled == pytest.approx(0.186, abs=0.005)
    assert joint == pytest.approx(0.144, abs=0.005)


@pytest.mark.parametrize(("separation", "off"), [(0.5, 0), (1.0, 25), (3.0, 25)])
def test_the_joint_scoring_switches_wrong_links_off_where_ratslams_does(separation: float, off: int) -> None:
    """``joint`` (``exp_relax_joint``) must not let wrong links through that RatSLAM's fixed point catches: 5
    wrong links ``separation`` metres off, seeds 0–4, on the two-lap circle. Swept: at 0.5 m none is switched
    off by either (within the drift the 1.26 m links allow: where both break), at 1 and 3 m all 25 by both; the
    14 true closures stay on (until 2026-11-28 one at 3 m went off with the joint scoring: it fits the map, and a
    link that fits now comes back on at equal cost, ``_Problem.switch_back_on``)."""
    clean = _circle_graph()
    n = clean[1].size
    for joint in (False, True):
        switched, true_off = 0, 0
        for seed in range(5):
            result = _run(_with_false(clean, 5, separation, seed=seed)[0], joint)
            switched += int(np.count_nonzero(~result.active[n:]))
            true_off += int(np.count_nonzero(~result.active[:n]))
        assert switched == off
        assert true_off == 0


def test_the_check_passes_the_switches_as_they_stood_with_the_links_added_since_off(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The status quo of a robust check (:func:`core.robust._search`): the previous check's switches, new links off."""
    em = _lap_map(departing())
    em.settle()
    before = em.link_count
    assert em.add_link_raw(3, 11, np.array([0.1, 0.0, 0.0, 0.0]), 1.0, 0.1, LinkKind.LOOP)
    assert em.add_link_raw(5, 13, np.array([0.1, 0.0, 0.0, 0.0]), 1.0, 0.1, LinkKind.LOOP)
    seen: list[np.ndarray] = []
    original = robust.switch_off_outliers

    def spy(*args: object, **kwargs: object) -> robust.RobustResult:
        seen.append(np.asarray(kwargs["previous"]).copy())
        return original(*args, **kwargs)

    monkeypatch.setattr("core.experience_map.switch_off_outliers", spy)
    em.settle()
    assert seen and seen[0].tolist() == [True] * before + [False, False]
    assert em.link_active.tolist() == [True] * before + [False, False]  # both wrong links off, the closures on


def test_the_status_quo_keeps_the_new_links_that_alone_join_the_map() -> None:
    """Links added since the last check can be all that joins two parts (a merge's): the status-quo start keeps
    them on instead of solving a disconnected graph (``Factor is exactly singular``: ``twin-overlap`` 20 m with
    turns alike, seed 5, session 2), and the answer keeps the true closures and drops the wrong link."""
    truth, src, dst, transform, kind, distance = _circle_graph()
    cut = np.flatnonzero((src == STEPS - 1) & (dst == STEPS))  # lap 2 joined to lap 1 by its closures only
    keep = np.ones(src.size, dtype=bool)
    keep[cut] = False
    graph = (truth, src[keep], dst[keep], transform[keep], kind[keep], distance[keep])
    graph, _ = _with_false(graph, 1, 3.0, seed=1)
    truth, src, dst, transform, kind, distance = graph
    previous = kind == 0  # the two laps' odometry stood before; every closure and the wrong link are new
    start = np.zeros_like(truth)
    start[0] = truth[0]
    anchor = component_anchors(truth.shape[0], src, dst)
    result = switch_off_outliers(start, src, dst, transform, kind, distance, anchor, DRIFT, previous=previous)
    assert result.active[kind == 0].all() and np.isfinite(result.pose).all()
    assert result.active[:-1].all() and not result.active[-1]  # the closures on, the wrong link off


def _two_parts_and_two_bridges(false_first: bool):
    """Part A (0-9, along x) and part B (10-19, 5 m to its left), joined only by two new merge links: the true one
    (4 → 14) and a false one (2 → 12) that puts B turned by π; the poses as they stand are the truth."""
    n = 20
    truth = np.zeros((n, 4))
    truth[:10, 0] = np.arange(10.0)
    truth[10:, 0] = np.arange(10.0)
    truth[10:, 1] = 5.0
    src = np.concatenate([np.arange(9), np.arange(10, 19)])
    dst = src + 1
    transform = _relative(truth[src], truth[dst])
    true_link = (4, 14, np.array([0.0, 5.0, 0.0, 0.0]))
    false_link = (2, 12, np.array([3.0, -4.0, 0.0, math.pi]))
    bridges = [false_link, true_link] if false_first else [true_link, false_link]
    src = np.concatenate([src, [b[0] for b in bridges]])
    dst = np.concatenate([dst, [b[1] for b in bridges]])
    transform = np.concatenate([transform, np.stack([b[2] for b in bridges])])
    kind = np.concatenate([np.zeros(18, dtype=np.int8), np.full(2, 2, dtype=np.int8)])
    distance = np.linalg.norm(transform[:, :3], axis=1)
    return truth, src, dst, transform, kind, distance


@pytest.mark.parametrize("false_first", [True, False])
def test_of_two_bridges_that_cost_the_same_the_one_the_map_stood_on_stays(false_first: bool) -> None:
    """Either merge link alone joins part B without strain (a tie of the TLS cost, the other one an outlier either
    way): the one that fits the map as it stands stays on (offline merge of ``symmetric`` seed 4: a false
    relocalisation's odometry link, switched off in its own map, won on rounding noise and turned session 2's
    first lap by 3.6 rad; merged APE 16 m)."""
    truth, src, dst, transform, kind, distance = _two_parts_and_two_bridges(false_first)
    anchor = component_anchors(truth.shape[0], src, dst)
    result = switch_off_outliers(truth, src, dst, transform, kind, distance, anchor, DRIFT, previous=kind == 0)
    true_index, false_index = (19, 18) if false_first else (18, 19)
    assert result.active[true_index] and not result.active[false_index]
    assert result.active[kind == 0].all()
    assert np.abs(result.pose[:, :3] - truth[:, :3]).max() < 1e-6  # the map as it stood: the true place


def test_chain_headings_join_parts_by_a_link_that_is_on_where_only_avoided_links_join_them() -> None:
    truth, src, dst, transform, kind, _ = _two_parts_and_two_bridges(false_first=True)
    anchor = component_anchors(truth.shape[0], src, dst)
    avoid = kind != 0
    by_order = chain_headings(truth[:, 3], src, dst, transform, avoid, anchor)
    assert by_order[10:] == pytest.approx(np.full(10, math.pi))  # link order: through the false link, first
    off = np.zeros(src.size, dtype=bool)
    off[18] = True  # the false link, switched off as the map stands
    by_status = chain_headings(truth[:, 3], src, dst, transform, avoid, anchor, off)
    assert by_status == pytest.approx(truth[:, 3])  # through the true link


@pytest.mark.parametrize("false", [True, False])
def test_an_odometry_link_a_check_switched_off_stays_switchable_without_its_reckoning_link(false: bool) -> None:
    """An odometry link that is off (a relocalisation's, whose reckoning link a merge no longer holds: ``symmetric``
    seed 7 offline) is decided by the check like a loop link: false (3 → 11, 0.1 m claimed) it stays off
    and the map stays clean; true (3 → 5 at its exact relative pose) it comes back on. Were it not switchable,
    the check would have to turn the false one on, and that would bend the lap."""
    em = _lap_map(departing())
    em.settle()
    clean = em.poses.copy()
    src, dst = (3, 11) if false else (3, 5)
    step = np.array([0.1, 0.0, 0.0, 0.0]) if false else _relative(clean[[3]], clean[[5]])[0]
    assert em.add_link_raw(src, dst, step, 1.0, float(np.linalg.norm(step[:3])), LinkKind.ODOMETRY, active=False)
    assert em.add_link_raw(2, 10, np.array([0.1, 0.0, 0.0, 0.0]), 1.0, 0.1, LinkKind.LOOP)  # a new link: a check
    em.settle()
    assert em.link_active[-2] == (not false) and not em.link_active[-1]
    assert _pose_gap(em.poses, clean) < 1e-3


def _two_parallel_sessions() -> tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray]:
    """Session A: 0-9 along x (1 m odometry links); session B: 10-19 along x at y = 1; one merge link 9 → 19.
    Returns the poses, (src, dst, transform, distance) and which links may be switched (the merge link)."""
    pose = np.zeros((20, 4))
    pose[:10, 0] = pose[10:, 0] = np.arange(10.0)
    pose[10:, 1] = 1.0
    src = np.r_[np.arange(9), np.arange(10, 19), 9]
    dst = np.r_[np.arange(1, 10), np.arange(11, 20), 19]
    transform = np.zeros((19, 4))
    transform[:18, 0] = 1.0
    transform[18] = [0.0, 1.0, 0.0, 0.0]
    distance = np.linalg.norm(transform[:, :3], axis=1)
    can = np.zeros(19, dtype=bool)
    can[18] = True
    return pose, (src, dst, transform, distance), can


def test_the_stored_map_refutes_a_link_between_sessions_that_the_path_between_its_ends_cannot_explain() -> None:
    """A link between the sessions claiming 8 m where the stored map holds 0 m (12 lies beside 2): over the 15 m path
    2 → 9 → 19 → 12 the map allows 0.1·(15 + 1) + 3·1 = 4.6 m (drift·(L + s) + UNARY_REACH·s), 8/4.6 = 1.74 >
    UNARY_THRESHOLD: refuted. Must still pass: the true link 5 → 15; the same wrong link 6 m off (1.30); the wrong link
    when the stored map held it (nothing to test against); a wrong link within one session (the odometry joins
    its ends: :func:`contradicts_odometry`'s test); the wrong link when session B is the running one (its links are
    not the stored map's: no path through the stored map joins the ends)."""
    pose, (src, dst, transform, distance), can = _two_parallel_sessions()
    extra_src, extra_dst = np.array([2, 5, 2, 0]), np.array([12, 15, 12, 8])
    extra = np.array([[8.0, 1.0, 0, 0], [0.0, 1.0, 0, 0], [6.0, 1.0, 0, 0], [0.0, 0.0, 0, 0]])
    graph = (np.r_[src, extra_src], np.r_[dst, extra_dst], np.r_[transform, extra],
             np.r_[distance, np.linalg.norm(extra[:, :3], axis=1)])  # fmt: skip
    can = np.r_[can, np.ones(4, dtype=bool)]
    stood = np.r_[np.ones(19, dtype=bool), np.zeros(4, dtype=bool)]
    drift = Drift(0.1, 0.1, 4.0)
    refuted = contradicts_the_map(pose, graph, can, can & ~stood, stood, 1.0, drift)
    assert refuted.tolist() == [False] * 19 + [True, False, False, False]
    running = stood.copy()
    running[9:18] = False  # session B's odometry links are the running session's, not the stored map's
    assert not contradicts_the_map(pose, graph, can, can & ~stood, running, 1.0, drift).any()
    stood[19] = True  # the wrong link as part of the stored map
    assert not contradicts_the_map(pose, graph, can, can & ~stood, stood, 1.0, drift).any()


# ---------------------------------------------------------------- the low-rank solve decides as the full solve


@contextmanager
def _low_rank_counted() -> Iterator[list[int]]:
    """Count the states the low-rank solve answers."""
    low_rank = SwitchedRelaxation.run_residuals
    used = [0]

    def counted(self: SwitchedRelaxation, active: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        found = low_rank(self, active)
        used[0] += found is not None
        return found

    SwitchedRelaxation.run_residuals = counted  # type: ignore[method-assign]
    try:
        yield used
    finally:
        SwitchedRelaxation.run_residuals = low_rank  # type: ignore[method-assign]


def _same_answer(run: Callable[[], tuple[np.ndarray, ...]]) -> int:
    """Assert that ``run`` answers bit for bit the same with every state solved in full; return low-rank states."""
    low_rank = SwitchedRelaxation.run_residuals
    with _low_rank_counted() as used:
        fast = run()
    SwitchedRelaxation.run_residuals = lambda _self, _active: None  # type: ignore[method-assign,assignment]
    try:
        full = run()
    finally:
        SwitchedRelaxation.run_residuals = low_rank  # type: ignore[method-assign]
    assert len(fast) == len(full)
    for a, b in zip(fast, full, strict=True):
        assert np.array_equal(a, b)
    return used[0]


def _answer(graph) -> tuple[np.ndarray, ...]:
    result = _run(graph)
    return result.active, result.z, result.pose, np.array([result.iterations])


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 25), st.sampled_from([0.5, 1.0, 2.0, 3.0, 5.0, 8.0]), st.integers(0, 2**16),
       st.integers(1, 3), st.floats(0.0, 0.01), st.floats(0.95, 1.05))  # fmt: skip
def test_the_low_rank_solve_switches_what_the_full_solve_switches_on_random_maps(
    count: int, separation: float, seed: int, laps: int, yaw_bias: float, scale: float
) -> None:
    """Differential: random circles with random wrong links, the search's answer bit for bit as with full solves."""
    graph, _ = _with_false(_circle_graph(laps=laps, yaw_bias=yaw_bias, scale=scale), count, separation, seed)
    assert _same_answer(lambda: _answer(graph)) > 0


@pytest.mark.parametrize(("count", "separation", "seed"),
                         [(1, 3.0, 1), (5, 3.0, 5), (10, 3.0, 10), (5, 8.0, 5), (20, 1.0, 3)]
                         + [(20, 3.0, seed) for seed in range(10)])  # fmt: skip
def test_the_low_rank_solve_switches_what_the_full_solve_switches_on_the_injected_maps(
    count: int, separation: float, seed: int
) -> None:
    graph, _ = _with_false(_circle_graph(), count, separation, seed)
    assert _same_answer(lambda: _answer(graph)) > 0


def _settled(em: ExperienceMap) -> tuple[np.ndarray, ...]:
    em.settle()
    return em.link_active.copy(), em.poses.copy(), np.array(em.links[0])


@pytest.mark.parametrize("false", [True, False])
def test_the_low_rank_solve_unfolds_a_relocalisation_as_the_full_solve(false: bool) -> None:
    """Standby reckoning links (a relocalisation's fold) through the low-rank solve: the same map bit for bit."""
    assert _same_answer(lambda: _settled(_fold_map(departing(), false=false)[0])) > 0
    assert _same_answer(lambda: _settled(_twice_relocalised_map(first_false=false)[0])) > 0


# ---------------------------------------------------------------- the compiled scoring decides as the numpy one


@contextmanager
def _scored_by(path: str) -> Iterator[list[int]]:
    """Score every state by one path, and count the states the compiled one answered.

    ``compiled``: :class:`core._switched_kernel.CompiledScoring` on any graph (in use from ``COMPILED_FROM`` links of
    the 2-core on); ``numpy``: the low-rank numpy path (:meth:`SwitchedRelaxation.run_residuals`); ``full``: every
    state solved in full.
    """
    compiled_from, low_rank, score = robust.COMPILED_FROM, SwitchedRelaxation.run_residuals, CompiledScoring.score
    used = [0]

    def counted(self: CompiledScoring, active: np.ndarray) -> tuple[np.ndarray, float, bool] | None:
        found = score(self, active)
        used[0] += found is not None
        return found

    robust.COMPILED_FROM = 0 if path == "compiled" else 10**9
    CompiledScoring.score = counted  # type: ignore[method-assign]
    if path == "full":
        SwitchedRelaxation.run_residuals = lambda _self, _active: None  # type: ignore[method-assign,assignment]
    try:
        yield used
    finally:
        robust.COMPILED_FROM = compiled_from
        CompiledScoring.score = score  # type: ignore[method-assign]
        SwitchedRelaxation.run_residuals = low_rank  # type: ignore[method-assign]


def _same_answer_compiled(run: Callable[[], tuple[np.ndarray, ...]]) -> int:
    """Assert that ``run`` answers bit for bit the same by the compiled, the numpy and the full scoring; return the
    states the compiled one answered."""
    answers = {}
    for path in ("compiled", "numpy", "full"):
        with _scored_by(path) as used:
            answers[path] = run()
        if path == "compiled":
            compiled = used[0]
        else:
            assert used[0] == 0
    for path in ("numpy", "full"):
        assert len(answers[path]) == len(answers["compiled"])
        for a, b in zip(answers["compiled"], answers[path], strict=True):
            assert np.array_equal(a, b), path
    return compiled


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 25), st.sampled_from([0.5, 1.0, 2.0, 3.0, 5.0, 8.0]), st.integers(0, 2**16),
       st.integers(1, 3), st.floats(0.0, 0.01), st.floats(0.95, 1.05), st.floats(0.0, 0.3))  # fmt: skip
def test_the_compiled_scoring_switches_what_the_numpy_and_full_solves_switch_on_random_maps(
    count: int, separation: float, seed: int, laps: int, yaw_bias: float, scale: float, dz: float
) -> None:
    """Differential: random circles (climbing or flat) with random wrong links; the search's answer bit for bit the
    same whichever path scores its states, and the compiled one scored some of them."""
    graph, _ = _with_false(_circle_graph(laps=laps, yaw_bias=yaw_bias, scale=scale, dz=dz), count, separation, seed)
    assert _same_answer_compiled(lambda: _answer(graph)) > 0


@pytest.mark.parametrize("false", [True, False])
def test_the_compiled_scoring_unfolds_a_relocalisation_as_the_full_solve(false: bool) -> None:
    """Standby reckoning links and their reach (the cost's overreach term) through the compiled scoring."""
    assert _same_answer_compiled(lambda: _settled(_fold_map(departing(), false=false)[0])) > 0
    assert _same_answer_compiled(lambda: _settled(_twice_relocalised_map(first_false=false)[0])) > 0


def _problems(graph) -> tuple[_Problem, _Problem]:
    """Two problems over one graph, the first scored by the compiled path, the second by the numpy one."""
    truth, src, dst, transform, kind, distance = graph
    can = switchable(kind)
    anchor = component_anchors(truth.shape[0], src, dst)
    start = truth.copy()
    start[:, 3] = chain_headings(truth[:, 3], src, dst, transform, can, anchor)
    out = []
    for path in ("compiled", "numpy"):
        problem = _Problem(start, src, dst, transform, can, anchor, link_length(distance, kind), DRIFT, 400)
        with _scored_by(path):
            problem._prepared()
        out.append(problem)
    return out[0], out[1]


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**16), st.integers(0, 20), st.floats(0.0, 0.3))
def test_the_compiled_scoring_gives_the_numpy_scores_on_random_switches(seed: int, count: int, dz: float) -> None:
    """Each state's ``z`` and cost from the compiled path against the numpy path's, on random sets of switches (a
    new reference every so often, up to 40 links changed at once): equal to 1e-9 (the search decides outside 1e-6).
    """
    graph, _ = _with_false(_circle_graph(laps=2, dz=dz), count, 3.0, seed)
    compiled, numpy_path = _problems(graph)
    assert compiled._scorer is not None and numpy_path._scorer is None
    rng = np.random.default_rng(seed)
    can = np.flatnonzero(compiled.can)
    scored = 0
    for _ in range(30):
        active = np.ones(compiled.src.size, dtype=bool)
        active[rng.choice(can, size=rng.integers(0, min(40, can.size) + 1), replace=False)] = False
        active = compiled.couple(active)
        fast, slow = compiled.state(active), numpy_path.state(active)
        assert (fast.solved is None) == (slow.solved is None)
        if fast.solved is None:  # both low-rank: the compiled answer is the numpy one to rounding
            scored += 1
            assert np.allclose(fast.z, slow.z, rtol=1e-9, atol=1e-9)
            assert fast.cost == pytest.approx(slow.cost, rel=1e-9, abs=1e-9)
        else:
            assert np.array_equal(fast.z, slow.z)
    assert scored > 0


def test_the_compiled_scoring_scores_a_wrong_link_as_the_numpy_path_does() -> None:
    """One wrong link of 3 m on a clean double lap: with it on, its ``z`` exceeds c̄ and the cost charges it an
    outlier's worth; switched off, every ``z`` falls back within c̄ — by both paths alike."""
    clean = _circle_graph()
    graph, injected = _with_false(clean, 1, 3.0, seed=1)
    assert injected == 1
    compiled, numpy_path = _problems(graph)
    wrong = graph[1].size - 1
    for active in (np.ones(graph[1].size, dtype=bool), np.r_[np.ones(graph[1].size - 1, dtype=bool), False]):
        fast, slow = compiled.state(active), numpy_path.state(active)
        assert np.allclose(fast.z, slow.z, rtol=1e-9, atol=1e-9)
        assert fast.cost == pytest.approx(slow.cost, rel=1e-9)
        if active[wrong]:
            assert fast.z[wrong] > DRIFT.threshold
            assert fast.cost > DRIFT.threshold**2
        else:  # the paired must-still-happen: without it the map fits
            assert fast.z[active].max() < DRIFT.threshold


def _series_problem() -> tuple[_Problem, int, int, int]:
    """A ring of 12 odometry links and two closures in series through experience 12 (2 → 12 → 8), 3 m off.

    Both closures carry the same residual (experience 12 has no other link): only rounding orders them. A
    third closure, 0 → 6, is 1 m off: its ``z`` stands apart.
    """
    n = 12
    angle = 2 * math.pi * np.arange(n) / n
    ring = np.stack([5 * np.cos(angle), 5 * np.sin(angle), np.zeros(n), angle + math.pi / 2], 1)
    truth = np.vstack([ring, [[0.0, 0.0, 0.0, 0.0]]])
    src = np.r_[np.arange(n), 2, 12, 0]
    dst = np.r_[(np.arange(n) + 1) % n, 12, 8, 6]
    transform = _relative(truth[src], truth[dst])
    transform[n + 1, 0] += 3.0
    transform[n + 2, 1] += 1.0
    kind = np.r_[np.zeros(n), 1, 1, 1].astype(np.int8)
    can = switchable(kind)
    anchor = component_anchors(truth.shape[0], src, dst)
    start = truth.copy()
    start[:, 3] = chain_headings(truth[:, 3], src, dst, transform, can, anchor)
    distance = np.linalg.norm(transform[:, :3], axis=1)
    problem = _Problem(start, src, dst, transform, can, anchor, link_length(distance, kind), DRIFT, 400)
    return problem, n, n + 1, n + 2


def test_a_tie_that_rounding_would_order_is_decided_on_the_full_solve() -> None:
    problem, first, second, apart = _series_problem()
    state = problem.state(np.ones(problem.src.size, dtype=bool))
    assert state.solved is None  # the low-rank solve answered
    assert state.z[first] == pytest.approx(state.z[second], rel=1e-9)  # the series pair: equal but for rounding
    assert abs(state.z[first] - state.z[apart]) > 0.1
    decided = problem.decided(state, np.array([first, second]), top=True)
    assert decided.solved is not None  # solved in full: its rounding orders them as the check always has
    assert np.array_equal(decided.z, problem.exact(state).z)
    # and must not: links whose z stand apart keep the low-rank answer
    assert problem.decided(state, np.array([first, apart]), top=True) is state


def _forward_lap(view: bool, error_m: float, false_m: float | None = None) -> ExperienceMap:
    """Two laps of a 32-gon (0.5 m links, a yaw-rate bias); every 4th experience of lap 2 is closed onto its lap-1
    twin by a view that accepted the robot ``error_m`` to the side and 0.05 rad turned, alternately left and right
    (a forward camera's match: ``exp_delta_pc_threshold`` 2 cells of 0.25 m, ±5 columns of 75°/60). ``false_m``
    adds a look-alike's closure 3 → 19, that far from the truth."""
    params = departing(template_x_size=60, vt_shift_match=5, camera_fov_deg=75.0, exp_delta_pc_threshold=2.0,
                       pc_cell_x_size=0.25, exp_robust_view=view, exp_initial_em_deg=0.0)  # fmt: skip
    em = ExperienceMap(params, 3)
    em.create_experience(0, np.zeros(3), 0.0, 0)
    for i in range(1, 65):
        em.on_odo(Motion(0.5, 0.0, 0.0, 2 * math.pi / 32 + 0.004, 1.0))
        em.create_experience(i, np.zeros(3), float(i), 0)
        if i >= 32 and (i - 32) % 4 == 0:
            side = error_m if (i // 4) % 2 else -error_m
            em.add_link_raw(i - 32, i, np.array([0.0, side, 0.0, math.copysign(0.05, side)]), 0.0, 0.0,
                            LinkKind.LOOP)  # fmt: skip
    if false_m is not None:
        em.add_link_raw(3, 19, np.array([false_m, 0.0, 0.0, 0.0]), 1.0, false_m, LinkKind.LOOP)
    em.settle()
    return em


def test_a_view_link_within_its_closure_gate_stays_on_and_a_look_alike_still_goes_off() -> None:
    """``exp_robust_view``: a forward view's closure 0.5 m aside and 3° turned lies within the gate the pose cells
    closed it through (2 cells of 0.25 m); counting that in its ``z`` keeps all 9 true closures on (as precise as
    odometry, 5 of them went off), while a closure 3 m off (a look-alike) goes off either way, and views 0.8 m aside
    — beyond the gate — still go off."""
    loops = _forward_lap(True, 0.5).links[5] == int(LinkKind.LOOP)
    assert int(loops.sum()) == 9
    assert _forward_lap(True, 0.5).link_active[loops].all()  # must: within the gate, kept
    assert (~_forward_lap(False, 0.5).link_active[loops]).sum() >= 3  # as precise as odometry they went off
    with_false = _forward_lap(True, 0.5, false_m=3.0)
    assert not with_false.link_active[-1] and with_false.link_active[:-1].all()  # must not: the look-alike stays off
    assert (~_forward_lap(True, 0.8).link_active[loops]).sum() >= 2  # beyond the gate: not every view link is kept

"""Pairwise consistency of loop links (core.pcm): cycle errors by hand, tree paths, the greedy clique.

The pose algebra it composes cycles with is core.se3, tested in test_se3.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from core.angles import wrap_angle
from core.pcm import (
    TreePaths,
    greedy_clique,
    heading_bias,
    heading_consistency,
    map_consistency,
    pair_consistency,
    single_consistency,
)
from core.se3 import compose, relative


@given(st.integers(2, 40), st.integers(0, 10_000))
@settings(max_examples=40, deadline=None)
def test_tree_paths_equal_shortest_paths_on_a_random_forest(n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    child = np.arange(1, n)
    parent = np.array([rng.integers(0, c) for c in child])
    cut = rng.random(child.size) < 0.15  # some edges missing: a forest of several trees
    src, dst, length = parent[~cut], child[~cut], rng.uniform(0.1, 3.0, int((~cut).sum()))
    roots = np.zeros(n, dtype=bool)
    roots[0] = True
    roots[child[cut]] = True
    paths = TreePaths(n, src, dst, length, roots)
    expected = dijkstra(csr_matrix((length, (src, dst)), shape=(n, n)), directed=False)
    a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    got = paths.distance(a.ravel(), b.ravel()).reshape(n, n)
    assert np.array_equal(np.isinf(got), np.isinf(expected))
    assert np.allclose(got[np.isfinite(got)], expected[np.isfinite(expected)])


@given(st.integers(2, 200), st.integers(0, 10_000))
@settings(max_examples=30, deadline=None)
def test_the_compiled_common_ancestors_are_numpys(n: int, seed: int) -> None:
    """core._tree_kernel lifts each pair on its own: the same ancestors as the numpy passes (a forest of chains and
    branches, pairs across trees included)."""
    from core._tree_kernel import lowest_common_ancestors

    rng = np.random.default_rng(seed)
    child = np.arange(1, n)
    parent = np.array([rng.integers(max(0, c - 3), c) for c in child])  # deep trees: many lifting levels
    cut = rng.random(child.size) < 0.05
    roots = np.zeros(n, dtype=bool)
    roots[0] = True
    roots[child[cut]] = True
    paths = TreePaths(n, parent[~cut], child[~cut], rng.uniform(0.1, 3.0, int((~cut).sum())), roots)
    a, b = rng.integers(0, n, 500), rng.integers(0, n, 500)
    joined = paths.component[a] == paths.component[b]
    assert np.array_equal(lowest_common_ancestors(paths.up, paths.depth, a, b)[joined], paths.ancestors(a, b)[joined])


@given(st.integers(2, 40), st.integers(0, 10_000))
@settings(max_examples=40, deadline=None)
def test_tree_paths_along_counts_links_walked_against_their_direction_negative(n: int, seed: int) -> None:
    """``along(a, b)``: the metres from a to b with each link counted + when walked from its source to its
    destination, − against it. Independently: walk each node up to its tree's root summing the signed
    lengths; the path a → b is a's walk minus b's (the shared part cancels)."""
    rng = np.random.default_rng(seed)
    child = np.arange(1, n)
    parent = np.array([rng.integers(0, c) for c in child])
    length = rng.uniform(0.1, 3.0, child.size)
    forward = rng.random(child.size) < 0.5  # the link runs parent → child, else child → parent
    src, dst = np.where(forward, parent, child), np.where(forward, child, parent)
    roots = np.zeros(n, dtype=bool)
    roots[0] = True
    paths = TreePaths(n, src, dst, length, roots)
    up = np.zeros(n)  # signed metres from each node up to the root
    for node in range(1, n):
        k, total = node, 0.0
        while k != 0:
            edge = k - 1
            total += -length[edge] if forward[edge] else length[edge]  # walked child → parent
            k = int(parent[edge])
        up[node] = total
    a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    got = paths.along(a.ravel(), b.ravel()).reshape(n, n)
    assert np.allclose(got, up[:, None] - up[None, :])
    assert np.all(np.abs(got) <= paths.distance(a.ravel(), b.ravel()).reshape(n, n) + 1e-9)


def test_heading_bias_by_hand() -> None:
    """Rates E_ψ/S: three long true cycles at −0.005 rad/m, a mirror cycle (π + b·S over 130 m: 0.019 rad/m,
    more than a heading drifts) and a short one (5 m: a view's heading error) left out; the median of the rest."""
    turn = np.array([0.4, -0.45, 0.5, math.pi - 0.65, 0.3])
    along = np.array([-80.0, 90.0, -100.0, 130.0, 5.0])
    assert heading_bias(turn, along) == pytest.approx(-0.005)
    assert heading_bias(turn[2:], along[2:]) is None  # one long true cycle: too few to tell
    assert heading_bias(turn, np.full(5, np.inf)) is None  # no path joins the ends
    # rates −0.005, −0.004 and 0.010, 0.011: two groups of two, 0.015 apart: the map cannot tell which is the bias
    assert heading_bias(np.array([-0.5, -0.4, 1.0, 1.1]), np.full(4, 100.0)) is None
    # with a third cycle agreeing with the first two (within ±0.006 of their centre) they win: the median
    assert heading_bias(np.array([-0.5, -0.4, -0.2, 1.0, 1.1]), np.full(5, 100.0)) == pytest.approx(-0.004)


def _biased_rings(laps: int, per_lap: int, bias: float) -> tuple[np.ndarray, TreePaths]:
    """A ring of ``per_lap`` 1 m steps driven ``laps`` times, dead-reckoned with odometry that turns ``bias``
    rad per metre more than the robot did (experience k, odometry links k → k+1)."""
    n = laps * per_lap
    pose = np.zeros((n, 4))
    step = 2.0 * math.pi / per_lap + bias
    for k in range(1, n):
        pose[k] = compose(pose[k - 1], np.array([1.0, 0.0, 0.0, step]))
    roots = np.zeros(n, dtype=bool)
    roots[0] = True
    return pose, TreePaths(n, np.arange(n - 1), np.arange(1, n), np.ones(n - 1), roots)


def _ring_closures(true_from: list[int], mirrors: list[tuple[int, int]]) -> tuple[np.ndarray, ...]:
    """True lap closures k → k − 40 and mirror ones (from, back) to the ring's opposite point ``back`` m earlier,
    all saying "same place, same heading", on a ring dead-reckoned with 0.008 rad/m of heading bias."""
    pose, paths = _biased_rings(10, 40, -0.008)
    src = np.array(true_from + [a for a, _ in mirrors])
    dst = np.array([k - 40 for k in true_from] + [a - back for a, back in mirrors])
    transform = np.zeros((src.size, 4))
    return pose, paths, src, dst, transform


@pytest.mark.parametrize("back", [20, 60, 100, 140, 180, 260])
def test_a_mirror_closure_is_told_from_the_odometrys_heading_bias_over_any_path(back: int) -> None:
    """The sweep over the cycle's length: odometry turning 0.008 rad/m too much (twice the simulator's), four
    true lap closures (40 m of odometry: their cycles turn b·S) and a false one from experience 300 to the
    ring's opposite point ``back`` metres earlier ("same place" where the truth is 12.7 m away and turned π: a
    mirror place), whose cycle turns π + b·S. With the bias taken out π is left, flagged while it exceeds
    BRIDGED_TURN + BIAS_TURN_DRIFT·L (to 468 m): z = 1.5·π/(0.8 + 0.005·L) by hand. Without the bias (one true
    closure: unknown) the turn, shrunk by the bias, passes for drift from 60 m on (the old rule)."""
    pose, paths, src, dst, transform = _ring_closures([60, 90, 120, 150], [(300, back)])
    z = single_consistency(pose, (src, dst, transform), paths, (1.0, 0.1, 0.1))
    assert np.all(z[:4] < 0.5)  # the true closures: their turn is the bias's
    assert z[4] == pytest.approx(1.5 * math.pi / (0.8 + 0.005 * (back + 1.0)), rel=1e-6)
    assert z[4] > 1.5
    unknown = single_consistency(pose, (src[3:], dst[3:], transform[3:]), paths, (1.0, 0.1, 0.1))
    assert (unknown[1] > 1.5) == (back < 60)


@pytest.mark.parametrize("mirrors", [1, 2, 3, 4, 5])
def test_mirror_closures_are_flagged_while_the_true_ones_outnumber_them(mirrors: int) -> None:
    """Where it breaks: the bias is the consensus of the long cycles, so ``mirrors`` mirror closures over 180 m
    (their rates, (π + b·S)/S = 0.0094 rad/m, agree with one another) against four true ones (−0.008) are
    flagged while fewer; as many: the map cannot tell, the bias is unknown and they pass as before; more: the
    bias is theirs and they pass too. The true closures are never flagged."""
    pose, paths, src, dst, transform = _ring_closures([60, 90, 120, 150], [(380 - 40 * k, 180) for k in range(mirrors)])
    z = single_consistency(pose, (src, dst, transform), paths, (1.0, 0.1, 0.1))
    assert np.all(z[:4] < 1.5)
    assert np.all(z[4:] > 1.5) == (mirrors < 4)
    assert np.all(z[4:] < 1.5) == (mirrors >= 4)


def _straight_chain(n: int = 10) -> tuple[np.ndarray, TreePaths]:
    """Experiences 1 m apart along x, heading 0, joined by odometry links of 1 m."""
    pose = np.zeros((n, 4))
    pose[:, 0] = np.arange(n)
    src = np.arange(n - 1)
    roots = np.zeros(n, dtype=bool)
    roots[0] = True
    return pose, TreePaths(n, src, src + 1, np.ones(n - 1), roots)


def test_pair_consistency_by_hand_on_a_straight_chain() -> None:
    pose, paths = _straight_chain()
    # three links back along the chain: two true (8→1 and 9→2 both say -7 m), one 1 m wrong (9→2 says -6 m)
    src, dst = np.array([8, 9, 9]), np.array([1, 2, 2])
    transform = np.array([[-7.0, 0, 0, 0], [-7.0, 0, 0, 0], [-6.0, 0, 0, 0]])
    z = pair_consistency(pose, src, dst, transform, paths, length=1.0, drift=0.1, yaw_drift=0.1)
    assert z[0, 1] == 0.0 and z[1, 0] == 0.0  # the true pair closes exactly
    # 8→1 against the wrong 9→2: cycle 8 → 9 (1 m) → 2 → 1 (1 m): error 1 m over L = 1 + 1 + 2·1 m
    assert math.isclose(z[0, 2], 1.0 / (0.1 * 4.0))
    assert math.isclose(z[1, 2], 1.0 / (0.1 * 2.0))  # same ends: L = 0 + 0 + 2 m
    assert np.all(np.diag(z) == 0.0)


def test_a_heading_error_counts_through_the_yaw_drift() -> None:
    pose, paths = _straight_chain()
    src, dst = np.array([8, 8]), np.array([1, 1])
    transform = np.array([[-7.0, 0, 0, 0], [-7.0, 0, 0, 0.2]])
    z = pair_consistency(pose, src, dst, transform, paths, length=1.0, drift=0.1, yaw_drift=0.05)
    # cycle E = T2 · T1⁻¹ = (-7, 0, 0, 0.2) ⊕ (7, 0, 0, 0): xy (-7 + 7cos 0.2, 7 sin 0.2), ψ 0.2
    ex, ey = -7 + 7 * math.cos(0.2), 7 * math.sin(0.2)
    assert math.isclose(z[0, 1], math.hypot(math.hypot(ex, ey) / (0.1 * 2), 0.2 / (0.05 * 2)))


def test_links_whose_ends_no_odometry_joins_are_consistent() -> None:
    pose = np.zeros((4, 4))
    pose[:, 0] = [0, 1, 10, 11]
    roots = np.array([True, False, True, False])
    paths = TreePaths(4, np.array([0, 2]), np.array([1, 3]), np.ones(2), roots)  # two separate chains
    z = pair_consistency(pose, np.array([0, 1]), np.array([2, 3]), np.array([[5.0, 0, 0, 0], [9.0, 0, 0, 0]]),
                         paths, 1.0, 0.1, 0.1)  # fmt: skip
    # cycle 0 → 1 (1 m) → 3 (link 2, +9 m) → 2 (1 m back) → 0 (link 1, -5 m): 4 m over L = 1 + 1 + 2 m
    assert math.isclose(z[0, 1], 4.0 / (0.1 * 4.0))
    paths_apart = TreePaths(4, np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.ones(4, bool))
    z_apart = pair_consistency(pose, np.array([0, 1]), np.array([2, 3]),
                               np.array([[5.0, 0, 0, 0], [9.0, 0, 0, 0]]), paths_apart, 1.0, 0.1, 0.1)  # fmt: skip
    assert z_apart[0, 1] == 0.0  # ... and without any odometry there is no cycle, no evidence


def test_greedy_clique_takes_links_by_degree_and_keeps_only_mutual_agreement() -> None:
    consistent = np.array([
        [1, 1, 1, 0, 1],
        [1, 1, 1, 0, 0],
        [1, 1, 1, 1, 0],
        [0, 0, 1, 1, 1],
        [1, 0, 0, 1, 1],
    ], dtype=bool)  # fmt: skip
    # degrees (self included) 4, 3, 4, 3, 3: 0 first, then 2 (agrees with 0), then 1 (agrees with 0 and 2);
    # 3 disagrees with 0, 4 with 2
    assert greedy_clique(consistent).tolist() == [True, True, True, False, False]


def test_single_consistency_by_hand_on_a_straight_chain() -> None:
    pose, paths = _straight_chain()
    # 8→1 true (-7 m); 8→1 saying "same place" (7 m wrong); 9→2 1 m short, turned 0.1 rad
    src, dst = np.array([8, 8, 9]), np.array([1, 1, 2])
    transform = np.array([[-7.0, 0, 0, 0], [0.0, 0, 0, 0], [-6.0, 0, 0, 0.1]])
    z = single_consistency(pose, (src, dst, transform), paths, (1.0, 0.1, 0.05))
    assert z[0] == 0.0
    # error 7 m against drift·L (L = 7 m of path + one link length) + UNARY_REACH (3) link lengths
    assert math.isclose(z[1], 7.0 / (0.1 * 8.0 + 3.0))
    # E = (-7, 0, 0, 0) ⊕ (-6, 0, 0, 0.1)⁻¹: the inverse is (6cos 0.1, -6sin 0.1, 0, -0.1)
    ex, ey = -7 + 6 * math.cos(0.1), -6 * math.sin(0.1)
    # its turn (0.1 rad) is one the odometry's heading explains: the allowance grows by 0.1 · L/π
    allowed = 0.1 * 8.0 + 3.0 + 0.1 * 8.0 / math.pi
    assert math.isclose(z[2], math.hypot(math.hypot(ex, ey) / allowed, 0.1 / (0.05 * 8.0)))
    apart = TreePaths(10, np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.ones(10, bool))
    assert np.isinf(single_consistency(pose, (src, dst, transform), apart, (1.0, 0.1, 0.05))).all()  # no path


def test_heading_consistency_by_hand_on_a_straight_chain() -> None:
    pose, paths = _straight_chain()
    # 8→1 true; 8→1 turned 0.3 rad (the cycle turns back by 0.3); 9→2 turned by π
    src, dst = np.array([8, 8, 9]), np.array([1, 1, 2])
    transform = np.array([[-7.0, 0, 0, 0], [-7.0, 0, 0, 0.3], [-7.0, 0, 0, math.pi]])
    turn, travelled = heading_consistency(pose, (src, dst, transform), paths)
    assert turn.tolist() == pytest.approx([0.0, -0.3, math.pi])
    assert travelled.tolist() == pytest.approx([7.0, 7.0, 7.0])


@given(st.integers(3, 30), st.integers(0, 10_000), st.floats(-3.0, 3.0), st.floats(-math.pi, math.pi))
@settings(max_examples=40, deadline=None)
def test_heading_consistency_returns_a_links_extra_turn_whatever_frame_the_map_is_in(
    n: int, seed: int, turn: float, frame_yaw: float
) -> None:
    """A link that says the route between its ends turned ``turn`` more than the poses do closes its cycle
    turned by ``-turn``; moving the whole map rigidly changes nothing."""
    rng = np.random.default_rng(seed)
    pose = np.column_stack([rng.uniform(-20, 20, (n, 3)), rng.uniform(-math.pi, math.pi, n)])
    roots = np.zeros(n, dtype=bool)
    roots[0] = True
    paths = TreePaths(n, np.arange(n - 1), np.arange(1, n), np.ones(n - 1), roots)
    src, dst = rng.integers(0, n, 5), rng.integers(0, n, 5)
    transform = compose(relative(pose[src], pose[dst]), np.array([0.0, 0.0, 0.0, turn]))
    got, travelled = heading_consistency(pose, (src, dst, transform), paths)
    assert np.allclose(wrap_angle(got + turn), 0.0, atol=1e-9)
    assert travelled.tolist() == pytest.approx(np.abs(src - dst).astype(float).tolist())
    moved = compose(np.array([3.0, -7.0, 1.0, frame_yaw]), pose)
    again, _ = heading_consistency(moved, (src, dst, transform), paths)
    assert np.allclose(wrap_angle(again - got), 0.0, atol=1e-9)


def _two_chains() -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Experiences 0-4 along x at y = 0 and 5-9 along x at y = 2 (1 m apart in each), joined by 4 → 9 (2 m) and a
    parallel 10 m link 9 → 4; experience 10 stands alone at the origin. Returns the poses and (src, dst, metres)."""
    pose = np.zeros((11, 4))
    pose[:5, 0] = pose[5:10, 0] = np.arange(5.0)
    pose[5:10, 1] = 2.0
    src = np.array([0, 1, 2, 3, 5, 6, 7, 8, 4, 9])
    dst = np.array([1, 2, 3, 4, 6, 7, 8, 9, 9, 4])
    metres = np.array([1.0] * 8 + [2.0, 10.0])
    return pose, (src, dst, metres)


def test_map_consistency_by_hand_on_two_chains_joined_at_one_end() -> None:
    pose, graph = _two_chains()
    # 0 → 5 true (2 m to the left); 0 → 5 saying "same place" (2 m off); 0 → 5 saying "20 m behind" (20 m off);
    # 0 → 10: no path
    src, dst = np.array([0, 0, 0, 0]), np.array([5, 5, 5, 10])
    transform = np.array([[0.0, 2, 0, 0], [0.0, 0, 0, 0], [-20.0, 2, 0, 0], [0.0, 0, 0, 0]])
    z = map_consistency(pose, (src, dst, transform), graph, (1.0, 0.1))
    # the shortest path 0 → 5 is 4 + 2 + 4 = 10 m (the parallel 10 m link is not taken): allowed 0.1·(10 + 1) + 3·1
    assert z.tolist() == pytest.approx([0.0, 2.0 / 4.1, 20.0 / 4.1, 0.0])
    # a miss that could not exceed UNARY_THRESHOLD (1.5) over any path: no search, 0
    assert map_consistency(pose, (src[1:2], dst[1:2], transform[1:2]), graph, (1.0, 0.1)).tolist() == [0.0]

"""Shortest paths by time and by distance: hand-worked graphs, and the contracted search against references.

The references are an independent heapq Dijkstra over the raw link list (hypothesis graphs made of
chains, junctions, pure cycles, parallel and self links, zero weights, separate parts) and plain scipy
Dijkstra over every experience (a large RatSLAM-like graph).
"""

from __future__ import annotations

import heapq
import itertools
import math

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse.csgraph import dijkstra

from core.paths import ExperienceGraph, NoPath, PathResult

Links = list[tuple[int, int, float, float]]


@pytest.fixture
def graph() -> ExperienceGraph:
    poses = np.arange(20, dtype=float).reshape(5, 4)
    src = np.array([0, 1, 0, 1, 3])
    dst = np.array([1, 2, 2, 0, 4])
    dt = np.array([1.0, 1.0, 5.0, 3.0, 2.0])
    dist = np.array([5.0, 5.0, 1.0, 0.5, 1.0])
    return ExperienceGraph(poses, src, dst, dt, dist)


def make(n: int, links: Links) -> ExperienceGraph:
    arr = np.asarray(links, dtype=float).reshape(-1, 4)
    poses = np.column_stack([np.arange(n, dtype=float), np.zeros((n, 3))])
    return ExperienceGraph(poses, arr[:, 0].astype(int), arr[:, 1].astype(int), arr[:, 2], arr[:, 3])


def test_time_weight_prefers_the_quick_route(graph: ExperienceGraph) -> None:
    result = graph.shortest_path(0, 2, "time")
    assert isinstance(result, PathResult)
    assert result.nodes == [0, 1, 2]
    assert result.cost == pytest.approx(2.0)
    assert result.poses[:, 0] == pytest.approx([0.0, 4.0, 8.0])


def test_distance_weight_prefers_the_short_route(graph: ExperienceGraph) -> None:
    result = graph.shortest_path(2, 0, "distance")
    assert isinstance(result, PathResult)
    assert result.nodes == [2, 0]
    assert result.cost == pytest.approx(1.0)


def test_parallel_links_keep_the_cheapest(graph: ExperienceGraph) -> None:
    result = graph.shortest_path(1, 0, "distance")
    assert isinstance(result, PathResult)
    assert result.cost == pytest.approx(0.5)


def test_disconnected_nodes_give_no_path(graph: ExperienceGraph) -> None:
    result = graph.shortest_path(0, 4, "time")
    assert isinstance(result, NoPath)
    assert (result.source, result.target) == (0, 4)


def test_same_node_and_bad_inputs(graph: ExperienceGraph) -> None:
    same = graph.shortest_path(3, 3)
    assert isinstance(same, PathResult) and same.nodes == [3] and same.cost == 0.0
    with pytest.raises(IndexError):
        graph.shortest_path(0, 9)
    with pytest.raises(IndexError):
        graph.shortest_path(-1, 0)
    with pytest.raises(ValueError, match="weight"):
        graph.shortest_path(0, 1, "hops")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="same length"):
        ExperienceGraph(np.zeros((3, 4)), np.array([0, 1]), np.array([1]), np.ones(2), np.ones(2))
    with pytest.raises(ValueError, match="outside"):
        ExperienceGraph(np.zeros((3, 4)), np.array([0]), np.array([3]), np.ones(1), np.ones(1))


def test_a_chain_is_left_for_a_shortcut_between_its_ends() -> None:
    # chain 0-1-2-3-4-5 (1 s per link) and a 0.5 s loop closure 0-5: 1 → 4 goes 1, 0, 5, 4 (2.5 s), not 3 s
    links = [(k, k + 1, 1.0, 1.0) for k in range(5)] + [(0, 5, 0.5, 9.0)]
    g = make(6, links)
    assert g.junction_count == 1  # every experience has degree 2: a pure cycle, whose lowest id is the junction
    by_time = g.shortest_path(1, 4, "time")
    assert isinstance(by_time, PathResult)
    assert by_time.nodes == [1, 0, 5, 4] and by_time.cost == pytest.approx(2.5)
    by_distance = g.shortest_path(1, 4, "distance")
    assert isinstance(by_distance, PathResult)
    assert by_distance.nodes == [1, 2, 3, 4] and by_distance.cost == pytest.approx(3.0)


def test_parallel_chains_and_a_loop_through_one_junction() -> None:
    # junctions 0 (degree 5) and 9 (degree 3); chains 0-1-2-9 (3 s) and 0-3-4-5-9 (2 s); a loop 0-6-7-8-0;
    # a dead end 9-10
    links = [(0, 1, 1.0, 1.0), (1, 2, 1.0, 1.0), (2, 9, 1.0, 1.0)]
    links += [(0, 3, 0.5, 2.0), (3, 4, 0.5, 2.0), (4, 5, 0.5, 2.0), (5, 9, 0.5, 2.0)]
    links += [(0, 6, 1.0, 1.0), (6, 7, 1.0, 1.0), (7, 8, 3.5, 3.5), (8, 0, 1.0, 1.0), (9, 10, 4.0, 4.0)]
    g = make(11, links)
    assert g.junction_count == 3  # 0, 9, 10
    cases = {
        (1, 5, "time"): ([1, 0, 3, 4, 5], 2.5),
        (1, 5, "distance"): ([1, 2, 9, 5], 4.0),
        (10, 6, "time"): ([10, 9, 5, 4, 3, 0, 6], 7.0),
        (7, 2, "distance"): ([7, 6, 0, 1, 2], 4.0),
        (6, 8, "time"): ([6, 0, 8], 2.0),
        (8, 6, "time"): ([8, 0, 6], 2.0),
        (6, 7, "time"): ([6, 7], 1.0),
        (7, 8, "time"): ([7, 6, 0, 8], 3.0),  # round the loop through 0, not the 3.5 s link
        (0, 9, "time"): ([0, 3, 4, 5, 9], 2.0),
    }
    for (a, b, weight), (nodes, cost) in cases.items():
        result = g.shortest_path(a, b, weight)  # type: ignore[arg-type]
        assert isinstance(result, PathResult)
        assert (result.nodes, result.cost) == (nodes, pytest.approx(cost)), (a, b, weight)


def test_pure_cycle_both_ways_round() -> None:
    ring = [2, 7, 4, 9, 1, 5]  # a ring of 6 experiences with scattered ids; 0, 3, 6, 8 stand alone
    dt = [1.0, 1.0, 1.0, 1.0, 1.0, 10.0]
    links = [(ring[k], ring[(k + 1) % 6], dt[k], 1.0) for k in range(6)]
    g = make(10, links)
    forward = g.shortest_path(5, 2, "time")  # the 10 s link 5-2 loses against the five 1 s links
    assert isinstance(forward, PathResult)
    assert forward.nodes == [5, 1, 9, 4, 7, 2] and forward.cost == pytest.approx(5.0)
    direct = g.shortest_path(5, 2, "distance")
    assert isinstance(direct, PathResult) and direct.nodes == [5, 2] and direct.cost == pytest.approx(1.0)
    assert isinstance(g.shortest_path(4, 3, "time"), NoPath)


def test_zero_weight_links_cost_one_nanosecond_each() -> None:
    g = make(4, [(0, 1, 0.0, 0.0), (1, 2, 0.0, 0.0), (2, 3, 0.0, 2.0)])
    result = g.shortest_path(3, 0, "time")
    assert isinstance(result, PathResult)
    assert result.nodes == [3, 2, 1, 0] and result.cost == pytest.approx(3e-9, rel=1e-6)


def test_non_finite_costs_are_missing_links_for_that_weight() -> None:
    g = make(3, [(0, 1, math.inf, 1.0), (1, 2, 1.0, math.nan), (0, 1, 2.0, math.nan)])
    by_time = g.shortest_path(0, 2, "time")
    assert isinstance(by_time, PathResult) and by_time.cost == pytest.approx(3.0)
    assert isinstance(g.shortest_path(0, 2, "distance"), NoPath)
    assert isinstance(g.shortest_path(1, 0, "distance"), PathResult)


# ------------------------------------------------------------------ against references
def reference(n: int, links: Links, weight: str, source: int) -> list[float]:
    """Costs from ``source`` by a textbook heapq Dijkstra over the raw links (costs at least 1e-9)."""
    column = 2 if weight == "time" else 3
    adjacency: list[list[tuple[int, float]]] = [[] for _ in range(n)]
    for link in links:
        a, b, cost = int(link[0]), int(link[1]), max(float(link[column]), 1e-9)
        if a != b and math.isfinite(cost):
            adjacency[a].append((b, cost))
            adjacency[b].append((a, cost))
    best = [math.inf] * n
    best[source] = 0.0
    queue = [(0.0, source)]
    while queue:
        d, node = heapq.heappop(queue)
        if d > best[node]:
            continue
        for other, cost in adjacency[node]:
            if d + cost < best[other]:
                best[other] = d + cost
                heapq.heappush(queue, (d + cost, other))
    return best


def check_path(result: PathResult | NoPath, n: int, links: Links, weight: str, source: int, target: int) -> None:
    """Assert ``result`` is a shortest path (or none) by the reference, valid link by link."""
    expected = reference(n, links, weight, source)[target]
    if math.isinf(expected):
        assert isinstance(result, NoPath), (source, target, weight)
        return
    assert isinstance(result, PathResult), (source, target, weight)
    assert result.cost == pytest.approx(expected, rel=1e-9, abs=1e-12)
    nodes = result.nodes
    assert nodes[0] == source and nodes[-1] == target
    assert len(set(nodes)) == len(nodes)  # a simple path
    column = 2 if weight == "time" else 3
    cheapest: dict[tuple[int, int], float] = {}
    for link in links:
        key = (min(int(link[0]), int(link[1])), max(int(link[0]), int(link[1])))
        cost = max(float(link[column]), 1e-9)
        if math.isfinite(cost):
            cheapest[key] = min(cost, cheapest.get(key, math.inf))
    total = sum(cheapest[(min(a, b), max(a, b))] for a, b in itertools.pairwise(nodes))
    assert total == pytest.approx(result.cost, rel=1e-9, abs=1e-12)
    assert result.poses[:, 0] == pytest.approx(nodes)


costs = st.one_of(st.just(0.0), st.integers(0, 4).map(float), st.floats(0.0, 10.0, allow_nan=False))


@st.composite
def graphs(draw: st.DrawFn) -> tuple[int, Links]:
    """Chains (open or closed) over random ids, extra links, self links and parallel copies."""
    n = draw(st.integers(1, 30))
    node = st.integers(0, n - 1)
    pairs: list[tuple[int, int]] = []
    for _ in range(draw(st.integers(0, 5 if n > 1 else 0))):
        walk = draw(st.lists(node, min_size=2, max_size=14, unique=True))
        if len(walk) >= 3 and draw(st.booleans()):
            walk.append(walk[0])  # a closed chain: a pure cycle, or a loop through a junction
        pairs += list(itertools.pairwise(walk))
    pairs += draw(st.lists(st.tuples(node, node), max_size=5))  # may be self links
    if pairs:
        pairs += draw(st.lists(st.sampled_from(pairs), max_size=4))  # parallel copies
    weights = draw(st.lists(st.tuples(costs, costs), min_size=len(pairs), max_size=len(pairs)))
    return n, [(a, b, t, d) for (a, b), (t, d) in zip(pairs, weights, strict=True)]


@given(case=graphs(), data=st.data())
@settings(max_examples=150, deadline=None)
def test_contracted_search_matches_a_plain_dijkstra(case: tuple[int, Links], data: st.DataObject) -> None:
    n, links = case
    g = make(n, links)
    # every pair from a few sources, both weights: chain ends, junctions, same chain, separate parts
    for source in data.draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=3, unique=True)):
        for target in range(n):
            for weight in ("time", "distance"):
                check_path(g.shortest_path(source, target, weight), n, links, weight, source, target)  # type: ignore[arg-type]


def test_a_large_ratslam_like_graph_matches_scipy() -> None:
    # five laps of a 2,000-experience route: odometry chains, loop closures onto the first lap every
    # ~37 experiences, a few zero-length links and repeated closures (parallel links)
    rng = np.random.default_rng(7)
    n = 10_000
    src = np.arange(n - 1)
    dst = src + 1
    laps = np.arange(2_000, n, 37)
    closures = np.column_stack([laps, laps % 2_000])
    src = np.concatenate([src, closures[:, 0], closures[:40, 0]])
    dst = np.concatenate([dst, closures[:, 1], closures[:40, 1]])
    dt = rng.uniform(0.0, 1.0, src.size)
    dt[rng.choice(src.size, 50, replace=False)] = 0.0
    distance = rng.uniform(0.1, 2.0, src.size)
    poses = rng.normal(size=(n, 4))
    g = ExperienceGraph(poses, src, dst, dt, distance)
    assert g.junction_count < n // 10
    lo, hi = np.minimum(src, dst), np.maximum(src, dst)
    for weight, cost in (("time", dt), ("distance", distance)):
        ranked = np.lexsort((cost, hi, lo))  # parallel links: keep the cheapest
        first = np.ones(ranked.size, dtype=bool)
        first[1:] = np.diff(lo[ranked] * n + hi[ranked]) != 0
        keep = ranked[first]
        matrix = sp.csr_matrix((np.maximum(cost[keep], 1e-9), (lo[keep], hi[keep])), shape=(n, n))
        symmetric = (matrix + matrix.T).tocsr()
        sources = rng.integers(0, n, 6)
        expected = dijkstra(symmetric, directed=True, indices=sources)
        for row, source in enumerate(sources):
            for target in rng.integers(0, n, 15):
                result = g.shortest_path(int(source), int(target), weight)  # type: ignore[arg-type]
                assert isinstance(result, PathResult)
                assert result.cost == pytest.approx(expected[row, target], rel=1e-9)
                nodes = np.asarray(result.nodes)
                assert nodes[0] == source and nodes[-1] == target and np.unique(nodes).size == nodes.size
                steps = np.asarray(symmetric[nodes[:-1], nodes[1:]]).ravel()
                assert np.all(steps > 0)  # consecutive experiences are linked
                assert steps.sum() == pytest.approx(result.cost, rel=1e-9)
                assert np.array_equal(result.poses, poses[nodes])

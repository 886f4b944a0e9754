"""Shortest paths by time and by distance: hand-worked graphs, and the contracted search against references.

The references are an independent heapq Dijkstra over the raw link list (hypothesis graphs made of
chains, junctions, pure cycles, parallel and self links, zero weights, separate parts) and plain scipy
Dijkstra over every experience (a large RatSLAM-like graph, and hypothesis graphs whose distinct
power-of-two costs make every shortest path unique: node for node). The search that stops at its target
is checked against scipy's search run to the end on the same graph (hand-worked lines and squares, and
hypothesis graphs with tied weights), and a graph is queried by eight threads at once.
"""

from __future__ import annotations

import heapq
import itertools
import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse.csgraph import dijkstra

from core.contraction import Chains, ContractedGraph
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


# ------------------------------------------------------------------ the search stops at its target
def csr(n: int, edges: list[tuple[int, int, float]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (indptr, indices, data) of the undirected graph ``edges`` (both directions), rows sorted."""
    both = sorted([(a, b, w) for a, b, w in edges] + [(b, a, w) for a, b, w in edges])
    indptr = np.searchsorted(np.array([e[0] for e in both], dtype=np.int64), np.arange(n + 1))
    indices = np.array([e[1] for e in both], dtype=np.int64)
    return indptr.astype(np.int64), indices, np.array([e[2] for e in both], dtype=np.float64)


def settle(
    graph: tuple[np.ndarray, ...], starts: dict[int, float], ends: dict[int, float], bound: float = math.inf,
    points: np.ndarray | None = None, goal: np.ndarray | None = None, scale: float = 0.0,
    landmarks: np.ndarray | None = None, landmark_goal: np.ndarray | None = None,
):  # fmt: skip
    from core._path_kernel import settle as kernel

    n = graph[0].size - 1
    points = np.zeros((n, 3)) if points is None else points
    goal = np.zeros(3) if goal is None else goal
    landmarks = np.zeros((0, n)) if landmarks is None else landmarks
    landmark_goal = np.zeros(0) if landmark_goal is None else landmark_goal
    return kernel(*graph, np.array(list(starts), dtype=np.int64), np.array(list(starts.values())),
                  np.array(list(ends), dtype=np.int64), np.array(list(ends.values())), bound,
                  points, goal, scale, landmarks, landmark_goal)  # fmt: skip


def test_the_search_stops_at_the_target_and_still_reaches_a_far_one() -> None:
    # a line 0-1-…-9 of 1 s links: from 0 to 2 the search settles 0, 1, 2 (distances 0, 1, 2), reaches 3
    # (a tentative 3) and stops there (3 > 2): 4…9 are never reached
    line = csr(10, [(k, k + 1, 1.0) for k in range(9)])
    dist, pred = settle(line, {0: 0.0}, {2: 0.0})
    assert dist[:4].tolist() == [0.0, 1.0, 2.0, 3.0] and np.isinf(dist[4:]).all()
    assert pred[:4].tolist() == [-1, 0, 1, 2]
    # an end cost of 0.5 (the target 0.5 s along a chain from node 2): bound 2.5, the same stop
    dist, _ = settle(line, {0: 0.0}, {2: 0.5})
    assert np.isinf(dist[4:]).all()
    # a target at the far end is still reached, through every node
    dist, pred = settle(line, {0: 0.0}, {9: 0.0})
    assert dist.tolist() == [float(k) for k in range(10)] and pred.tolist() == [-1, *range(9)]
    # a direct way of 1.5 s (along a chain shared by source and target) bounds the search from the start:
    # node 2 is only reached (2 > 1.5), so the caller keeps the direct way
    dist, _ = settle(line, {0: 0.0}, {2: 0.0}, bound=1.5)
    assert dist[:3].tolist() == [0.0, 1.0, 2.0] and np.isinf(dist[3:]).all()


def test_two_ways_in_and_two_ways_out() -> None:
    # a square 0-1-2-3-0 of 1 s links with a 0.25 s diagonal 0-2; the source lies on a chain entering the
    # graph at 1 (4 s) and at 3 (0.5 s), the target on one leaving it at 0 (3 s) and at 2 (0.25 s).
    # Settled: 3 (0.5); 0 and 2 tie at 1.5 (0 first, the lower id: bound 1.5 + 3 = 4.5; 1 reached at 2.5);
    # 2 (bound 1.5 + 0.25 = 1.75); the next, 1 at 2.5, is past the bound. Best: 3 → 2 → out, 1.75 s.
    square = csr(4, [(0, 1, 1.0), (1, 2, 1.0), (2, 3, 1.0), (3, 0, 1.0), (0, 2, 0.25)])
    dist, pred = settle(square, {1: 4.0, 3: 0.5}, {0: 3.0, 2: 0.25})
    assert dist.tolist() == [1.5, 2.5, 1.5, 0.5] and pred.tolist() == [3, 0, 3, -1]
    assert min(dist[0] + 3.0, dist[2] + 0.25) == 1.75


@st.composite
def weighted_graphs(draw: st.DrawFn) -> tuple[int, list[tuple[int, int, float]], dict[int, float], dict[int, float]]:
    """Random undirected graphs with tied weights, one or two ways in and out at random costs."""
    n = draw(st.integers(2, 25))
    node = st.integers(0, n - 1)
    pair = st.tuples(node, node).filter(lambda p: p[0] != p[1])
    pairs = draw(st.lists(pair, max_size=60, unique_by=lambda p: (min(p), max(p))))
    weight = st.one_of(st.integers(1, 4).map(float), st.floats(0.01, 10.0))
    edges = [(a, b, draw(weight)) for a, b in pairs]
    starts = draw(st.dictionaries(node, st.floats(0.0, 5.0), min_size=1, max_size=2))
    ends = draw(st.dictionaries(node, st.floats(0.0, 5.0), min_size=1, max_size=2))
    return n, edges, starts, ends


@given(case=weighted_graphs(), direct=st.one_of(st.just(math.inf), st.floats(0.0, 20.0)))
@settings(max_examples=300, deadline=None)
def test_the_stopped_search_equals_the_full_search_up_to_the_target(
    case: tuple[int, list[tuple[int, int, float]], dict[int, float], dict[int, float]], direct: float
) -> None:
    """Every node as near as the target's best way out has the full search's distance, bit for bit.

    The full search: scipy's Dijkstra to the end from a virtual node joined to the ways in (as the
    contracted search ran before it stopped at its target).
    """
    n, edges, starts, ends = case
    graph = csr(n, edges)
    dist, pred = settle(graph, starts, ends, direct)
    rows = [(a, b, w) for a, b, w in edges] + [(b, a, w) for a, b, w in edges] + [(n, s, c) for s, c in starts.items()]
    full = sp.csr_matrix(([r[2] for r in rows], ([r[0] for r in rows], [r[1] for r in rows])), shape=(n + 1, n + 1))
    expected = dijkstra(full, directed=True, indices=n)[:n]
    via = min(expected[e] + c for e, c in ends.items())
    got = min(dist[e] + c for e, c in ends.items())
    assert got == via if via <= direct else got >= via  # the target's cost, bit for bit, unless the direct way wins
    near = expected <= min(via, direct)
    assert dist[near].tobytes() == expected[near].tobytes()  # must: settled as the full search settles them
    assert np.all(dist >= expected)  # must not: a distance below the truth (the rest are upper bounds)
    weights = {(a, b): w for a, b, w in rows}
    for v in np.flatnonzero(np.isfinite(dist)):  # a reached node's pred chain adds up to its distance, in order
        chain = [int(v)]
        while pred[chain[-1]] >= 0:
            chain.append(int(pred[chain[-1]]))
        total = starts[chain[-1]]
        for u, w in itertools.pairwise(chain[::-1]):
            total += weights[(u, w)]
        assert total == dist[v]


def cheapest(n: int, links: Links, column: int) -> sp.csr_matrix:
    """Return the (n, n) upper-triangular matrix of the cheapest link of each pair (no self links)."""
    best: dict[tuple[int, int], float] = {}
    for link in links:
        a, b = sorted((int(link[0]), int(link[1])))
        if a != b:
            best[(a, b)] = min(float(link[column]), best.get((a, b), math.inf))
    rows = list(best)
    return sp.csr_matrix(([best[r] for r in rows], ([r[0] for r in rows], [r[1] for r in rows])), shape=(n, n))


@st.composite
def unique_path_graphs(draw: st.DrawFn) -> tuple[int, Links]:
    """Chains and extra links whose costs are distinct powers of two: every shortest path is unique, sums exact."""
    n = draw(st.integers(2, 25))
    node = st.integers(0, n - 1)
    pairs: list[tuple[int, int]] = []
    for _ in range(draw(st.integers(0, 4))):
        walk = draw(st.lists(node, min_size=2, max_size=10, unique=True))
        if len(walk) >= 3 and draw(st.booleans()):
            walk.append(walk[0])
        pairs += list(itertools.pairwise(walk))
    pairs = (pairs + draw(st.lists(st.tuples(node, node).filter(lambda p: p[0] != p[1]), max_size=8)))[:50]
    time_bits = draw(st.permutations(range(len(pairs))))
    distance_bits = draw(st.permutations(range(len(pairs))))
    return n, [(a, b, 2.0**t, 2.0**d) for (a, b), t, d in zip(pairs, time_bits, distance_bits, strict=True)]


@given(case=unique_path_graphs(), data=st.data())
@settings(max_examples=150, deadline=None)
def test_unique_shortest_paths_are_the_full_searchs_node_for_node(case: tuple[int, Links], data: st.DataObject) -> None:
    """With distinct power-of-two costs the path and its cost are those of a full scipy search, exactly."""
    n, links = case
    g = make(n, links)
    for weight, column in (("time", 2), ("distance", 3)):
        for source in data.draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=3, unique=True)):
            full, pred = dijkstra(cheapest(n, links, column), directed=False, indices=source, return_predecessors=True)
            for target in range(n):
                result = g.shortest_path(source, target, weight)  # type: ignore[arg-type]
                if math.isinf(full[target]):
                    assert isinstance(result, NoPath)
                    continue
                assert isinstance(result, PathResult)
                nodes = [target]
                while nodes[-1] != source:
                    nodes.append(int(pred[nodes[-1]]))
                assert result.nodes == nodes[::-1] and result.cost == full[target], (source, target, weight)


def test_threads_share_one_graph_without_a_lock() -> None:
    """Eight threads query one built graph at once and get the answers one thread gets; the graph is read-only."""
    rng = np.random.default_rng(3)
    n = 3_000  # three laps of a 1,000-experience route, closed onto the first lap every 23 experiences
    laps = np.arange(1_000, n, 23)
    src = np.concatenate([np.arange(n - 1), laps])
    dst = np.concatenate([np.arange(1, n), laps % 1_000])
    g = ExperienceGraph(rng.normal(size=(n, 4)), src, dst, rng.uniform(0.1, 1.0, src.size), np.ones(src.size))
    pairs = rng.integers(0, n, size=(400, 2)).tolist()
    alone = [g.shortest_path(a, b) for a, b in pairs]
    with ThreadPoolExecutor(8) as pool:
        together = list(pool.map(lambda p: g.shortest_path(*p), pairs * 4))
    for one, other in zip(alone * 4, together, strict=True):
        assert isinstance(one, PathResult) and isinstance(other, PathResult)
        assert (other.nodes, other.cost) == (one.nodes, one.cost)
    lo, hi = np.minimum(src, dst), np.maximum(src, dst)
    contracted = ContractedGraph(Chains.build(n, lo, hi), lo, hi, np.ones(src.size))
    for array in (contracted.indptr, contracted.indices, contracted.data, contracted.keys, contracted.via):
        with pytest.raises(ValueError, match="read-only"):
            array[0] = 0


# ------------------------------------------------------------------ A*: the straight line as a lower bound
def street_grid(rows: int, columns: int, cost_per_metre: float) -> ExperienceGraph:
    """Return a grid of streets 1 m apart: links along rows and columns, cost per metre ``cost_per_metre``."""
    ids = np.arange(rows * columns).reshape(rows, columns)
    src = np.concatenate([ids[:, :-1].ravel(), ids[:-1, :].ravel()])
    dst = np.concatenate([ids[:, 1:].ravel(), ids[1:, :].ravel()])
    r, c = np.divmod(np.arange(rows * columns), columns)
    poses = np.column_stack([c, r, np.zeros(r.size), np.zeros(r.size)]).astype(np.float64)
    cost = np.full(src.size, cost_per_metre)
    return ExperienceGraph(poses, src, dst, cost, np.ones(src.size))


def test_the_bound_is_the_least_cost_per_metre_of_any_link() -> None:
    from core.contraction import cost_per_metre

    # links of 2 s over 1 m and 3 s over 2 m: 1.5 s a metre is the least; a zero-length link sets no bound
    points = np.array([[0.0, 0, 0], [1, 0, 0], [3, 0, 0], [3, 0, 0]])
    lo, hi = np.array([0, 1, 2]), np.array([1, 2, 3])
    assert cost_per_metre(lo, hi, np.array([2.0, 3.0, 1e-9]), points) == pytest.approx(1.5, rel=1e-5)
    assert cost_per_metre(lo, hi, np.array([2.0, 3.0, 1e-9]), points) < 1.5  # never above it (rounding)
    # no positions, a NaN position, or nothing but zero-length links: no bound (the search is Dijkstra's)
    assert cost_per_metre(lo, hi, np.ones(3), None) == 0.0
    assert cost_per_metre(lo, hi, np.ones(3), np.where(np.arange(12).reshape(4, 3) == 4, np.nan, points)) == 0.0
    assert cost_per_metre(lo[2:], hi[2:], np.ones(1), points) == 0.0


def test_a_cheap_shortcut_lowers_the_bound_and_is_still_taken() -> None:
    # a 20 × 20 grid at 1 s a metre, and a closure between opposite corners (27 m apart) that costs 1 s:
    # from corner to corner the shortcut (1 s) must win over the streets (38 s), which an A* whose bound
    # ignored it (1 s a metre) would never look at
    poses = street_grid(20, 20, 1.0).poses
    ids = np.arange(400).reshape(20, 20)
    base_src = np.concatenate([ids[:, :-1].ravel(), ids[:-1, :].ravel(), [0]])
    base_dst = np.concatenate([ids[:, 1:].ravel(), ids[1:, :].ravel(), [399]])
    cost = np.concatenate([np.ones(base_src.size - 1), [1.0]])
    with_shortcut = ExperienceGraph(poses, base_src, base_dst, cost, cost)
    result = with_shortcut.shortest_path(0, 399)
    assert isinstance(result, PathResult) and result.nodes == [0, 399] and result.cost == 1.0
    found = with_shortcut.shortest_path(1, 398)  # 1 s to 0, the shortcut, 1 s on: 3 s against 36 s of streets
    assert isinstance(found, PathResult) and found.cost == pytest.approx(3.0)
    without = street_grid(20, 20, 1.0).shortest_path(1, 398)
    assert isinstance(without, PathResult) and without.cost == pytest.approx(36.0)


@given(seed=st.integers(0, 2**32 - 1), weight=st.sampled_from(["time", "distance"]))
@settings(max_examples=60, deadline=None)
def test_a_star_costs_are_the_full_searchs(seed: int, weight: str) -> None:
    """On random planar maps (links at 1–3× their straight length, some closures) every cost is scipy's."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(5, 120))
    points = np.cumsum(rng.normal(size=(n, 2)), axis=0)
    extra = rng.integers(0, n, size=(n // 5, 2))
    src = np.concatenate([np.arange(n - 1), extra[:, 0]])
    dst = np.concatenate([np.arange(1, n), extra[:, 1]])
    length = np.linalg.norm(points[src] - points[dst], axis=1)
    cost = length * rng.uniform(1.0, 3.0, src.size) + 1e-3
    poses = np.column_stack([points, np.zeros((n, 2))])
    g = ExperienceGraph(poses, src, dst, cost, cost)
    links = [(a, b, c, c) for a, b, c in zip(src.tolist(), dst.tolist(), cost.tolist(), strict=True)]
    full = dijkstra(cheapest(n, links, 2), directed=False)
    for source, target in rng.integers(0, n, size=(10, 2)).tolist():
        result = g.shortest_path(source, target, weight)  # type: ignore[arg-type]
        assert isinstance(result, PathResult)
        assert result.cost == pytest.approx(full[source, target], rel=1e-12, abs=1e-12)


def test_a_star_settles_fewer_junctions_than_dijkstra_on_a_grid() -> None:
    # must happen: on a 60 × 60 street grid at 2 s a metre, a query 40 m along the first street reaches a
    # fraction of the junctions Dijkstra reaches (a strip along the street against a quarter disc of radius
    # 40 m); must still: the same cost
    g = street_grid(60, 60, 2.0)
    graph = g._graphs["time"]
    assert graph.scale == pytest.approx(2.0, rel=1e-5)
    source, target = 0, 40
    ways = graph._ways(source, target), graph._ways(target, source)
    args = (
        {w[0]: w[1] for w in ways[0]}, {w[0]: w[1] for w in ways[1]}, math.inf, graph.junction_points,
    )
    graph_arrays = (graph.indptr, graph.indices, graph.data)
    dijkstra_dist, _ = settle(graph_arrays, *args, np.zeros(3), 0.0)
    a_star_dist, _ = settle(graph_arrays, *args, graph._goal(target), graph.scale)
    assert np.isfinite(a_star_dist).sum() * 3 < np.isfinite(dijkstra_dist).sum()
    result = g.shortest_path(source, target)
    assert isinstance(result, PathResult) and result.cost == pytest.approx(80.0)


def test_landmarks_are_farthest_first_and_every_connected_part_gets_one() -> None:
    from core.contraction import landmark_distances

    # two lines, 0-1-2-3 (1 s links) and 4-5 (2 s): from node 0 the farthest reached is 3, but 4 and 5 are
    # not reached at all, so the first landmark is 4 (the lowest id no one reaches); then 0 (farthest from
    # 4: not reached), then 3 (3 s from 0)
    graph = csr(6, [(0, 1, 1.0), (1, 2, 1.0), (2, 3, 1.0), (4, 5, 2.0)])
    rows = landmark_distances(*graph, count=3)
    assert rows.shape == (3, 6)
    assert rows[0].tolist() == [math.inf] * 4 + [0.0, 2.0]
    assert rows[1].tolist() == [0.0, 1.0, 2.0, 3.0, math.inf, math.inf]
    assert rows[2].tolist() == [3.0, 2.0, 1.0, 0.0, math.inf, math.inf]
    # queries in both parts still find their paths (a landmark in the other part bounds nothing)
    g = ExperienceGraph(np.zeros((6, 4)), np.array([0, 1, 2, 4]), np.array([1, 2, 3, 5]), np.array([1.0, 1, 1, 2]),
                        np.ones(4))  # fmt: skip
    for (source, target), cost in {(0, 3): 3.0, (5, 4): 2.0}.items():
        result = g.shortest_path(source, target)
        assert isinstance(result, PathResult) and result.cost == cost
    assert isinstance(g.shortest_path(0, 5), NoPath)

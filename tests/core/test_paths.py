"""Shortest paths by time and by distance, parallel links, and the no-path outcome."""

from __future__ import annotations

import numpy as np
import pytest

from core.paths import ExperienceGraph, NoPath, PathResult


@pytest.fixture
def graph() -> ExperienceGraph:
    poses = np.arange(20, dtype=float).reshape(5, 4)
    src = np.array([0, 1, 0, 1, 3])
    dst = np.array([1, 2, 2, 0, 4])
    dt = np.array([1.0, 1.0, 5.0, 3.0, 2.0])
    dist = np.array([5.0, 5.0, 1.0, 0.5, 1.0])
    return ExperienceGraph(poses, src, dst, dt, dist)


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
    with pytest.raises(ValueError, match="weight"):
        graph.shortest_path(0, 1, "hops")  # type: ignore[arg-type]

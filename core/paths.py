"""Shortest paths over the experience graph (OpenRatSLAM ``dijkstra_distance_between_experiences``).

The graph is contracted once (:mod:`core.contraction`: chains of degree-2 experiences between
junctions), so that a query runs an A* search over the junctions only (bounded below by the straight line
and by landmark distances), stopping at the target, and still returns an exact shortest path of the whole
graph. A built graph is read-only: threads share it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from core.arrays import BoolArray, FloatArray, IntArray
from core.contraction import Chains, ContractedGraph

Weight = Literal["time", "distance"]
_MIN_WEIGHT = 1e-9  # zero-length links stay edges of positive cost (so shortest paths stay simple)


@dataclass(frozen=True, slots=True)
class PathResult:
    """A shortest path: experience ids, their poses (N, 4: x, y, z, yaw) and the total cost."""

    nodes: list[int]
    poses: FloatArray
    cost: float
    weight: Weight


@dataclass(frozen=True, slots=True)
class NoPath:
    """The two experiences are not connected: a distinct outcome, not an exception."""

    source: int
    target: int
    weight: Weight


class ExperienceGraph:
    """An undirected weighted view of the experience links, built once and queried many times.

    Links are traversable in both directions, as OpenRatSLAM's path planner; edge weight is the link's
    Δt (time-optimal, as OpenRatSLAM) or its length (metric), at least ``1e-9`` (a zero-length link is
    still an edge). Parallel links keep the cheapest; self-links are ignored, and so is a link whose
    cost is not finite (for that weight). Construction takes a few vectorised csgraph passes
    (``O(L log L)`` for ``L`` links); a query one A* search over the junctions nearer than the target
    (see :mod:`core.contraction`). Queries take no lock and change nothing: any number of threads may run them.

    Raises:
        ValueError: the link arrays differ in length or name an experience that does not exist.
    """

    def __init__(
        self,
        poses: FloatArray,
        link_from: IntArray,
        link_to: IntArray,
        link_dt: FloatArray,
        link_distance: FloatArray,
    ) -> None:
        self.poses = np.asarray(poses, dtype=np.float64)
        n = self.poses.shape[0]
        self.size = n
        lo, hi, costs = _simple_links(n, link_from, link_to, {"time": link_dt, "distance": link_distance})
        self._graphs: dict[str, ContractedGraph] = {}
        shared: tuple[BoolArray, Chains] | None = None
        for name, cost in costs.items():
            usable = np.isfinite(cost)
            if shared is None or not np.array_equal(shared[0], usable):
                shared = (usable, Chains.build(n, lo[usable], hi[usable]))
            self._graphs[name] = ContractedGraph(shared[1], lo[usable], hi[usable], cost[usable], self.poses)

    @property
    def junction_count(self) -> int:
        """Return the number of junctions of the time graph (experiences of degree ≠ 2, one per pure cycle)."""
        return int(self._graphs["time"].chains.junctions.size)

    def shortest_path(self, source: int, target: int, weight: Weight = "time") -> PathResult | NoPath:
        """Return the shortest path from ``source`` to ``target`` (A* over the contracted graph).

        Raises:
            IndexError: an id is not an experience of this graph.
            ValueError: ``weight`` is not ``time`` or ``distance``.
        """
        if weight not in self._graphs:
            msg = f"unknown path weight {weight!r} (use 'time' or 'distance')"
            raise ValueError(msg)
        for node in (source, target):
            if not 0 <= node < self.size:
                msg = f"experience {node} does not exist (map has {self.size})"
                raise IndexError(msg)
        found = self._graphs[weight].search(int(source), int(target))
        if found is None:
            return NoPath(source, target, weight)
        cost, nodes = found
        return PathResult(nodes, self.poses[nodes], cost, weight)


def _simple_links(
    n: int, link_from: IntArray, link_to: IntArray, weights: dict[str, FloatArray]
) -> tuple[IntArray, IntArray, dict[str, FloatArray]]:
    """Return the distinct undirected links ``lo < hi`` and, per weight, the cheapest finite cost of each.

    Costs are raised to at least ``1e-9``; a pair whose links all have a non-finite cost gets NaN or inf.
    """
    src = np.asarray(link_from, dtype=np.int64).ravel()
    dst = np.asarray(link_to, dtype=np.int64).ravel()
    costs = {k: np.maximum(np.asarray(w, dtype=np.float64).ravel(), _MIN_WEIGHT) for k, w in weights.items()}
    if any(a.size != src.size for a in (dst, *costs.values())):
        msg = "link arrays (from, to, dt, distance) must have the same length"
        raise ValueError(msg)
    if src.size and (min(src.min(), dst.min()) < 0 or max(src.max(), dst.max()) >= n):
        msg = f"a link names an experience outside 0..{n - 1}"
        raise ValueError(msg)
    lo, hi = np.minimum(src, dst), np.maximum(src, dst)
    keep = np.flatnonzero(lo != hi)
    keep = keep[np.lexsort((hi[keep], lo[keep]))]
    lo, hi = lo[keep], hi[keep]
    first = np.ones(lo.size, dtype=bool)
    first[1:] = (lo[1:] != lo[:-1]) | (hi[1:] != hi[:-1])
    groups = np.flatnonzero(first)
    cheapest = {k: np.fmin.reduceat(w[keep], groups) if groups.size else w[:0] for k, w in costs.items()}
    return lo[first], hi[first], cheapest

"""Shortest paths over the experience graph (OpenRatSLAM ``dijkstra_distance_between_experiences``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

Weight = Literal["time", "distance"]
_MIN_WEIGHT = 1e-9  # zero-length links stay edges (csgraph drops explicit zeros)


@dataclass(frozen=True, slots=True)
class PathResult:
    """A shortest path: experience ids, their poses (N, 4: x, y, z, yaw) and the total cost."""

    nodes: list[int]
    poses: np.ndarray
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

    Links are traversable in both directions, as OpenRatSLAM's path planner; edge
    weight is the link's Δt (time-optimal, as OpenRatSLAM) or its length (metric).
    Parallel links keep the cheapest.
    """

    def __init__(
        self,
        poses: np.ndarray,
        link_from: np.ndarray,
        link_to: np.ndarray,
        link_dt: np.ndarray,
        link_distance: np.ndarray,
    ) -> None:
        self.poses = np.asarray(poses, dtype=np.float64)
        n = self.poses.shape[0]
        self.size = n
        self._graphs = {
            "time": _symmetric_min_graph(n, link_from, link_to, link_dt),
            "distance": _symmetric_min_graph(n, link_from, link_to, link_distance),
        }

    def shortest_path(self, source: int, target: int, weight: Weight = "time") -> PathResult | NoPath:
        """Return the shortest path from ``source`` to ``target`` by Dijkstra.

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
        if source == target:
            return PathResult([source], self.poses[[source]].copy(), 0.0, weight)
        dist, pred = dijkstra(self._graphs[weight], directed=False, indices=source, return_predecessors=True)
        if not np.isfinite(dist[target]):
            return NoPath(source, target, weight)
        nodes = [target]
        while nodes[-1] != source:
            nodes.append(int(pred[nodes[-1]]))
        nodes.reverse()
        return PathResult(nodes, self.poses[nodes].copy(), float(dist[target]), weight)


def _symmetric_min_graph(n: int, src: np.ndarray, dst: np.ndarray, weight: np.ndarray) -> sp.csr_matrix:
    """Build an (n, n) CSR graph keeping the minimum weight of parallel links, stored once per pair."""
    src = np.asarray(src, dtype=np.int64)
    dst = np.asarray(dst, dtype=np.int64)
    w = np.maximum(np.asarray(weight, dtype=np.float64), _MIN_WEIGHT)
    lo = np.minimum(src, dst)
    hi = np.maximum(src, dst)
    keep = lo != hi
    lo, hi, w = lo[keep], hi[keep], w[keep]
    if lo.size == 0:
        return sp.csr_matrix((n, n))
    order = np.lexsort((w, hi, lo))
    lo, hi, w = lo[order], hi[order], w[order]
    first = np.ones(lo.size, dtype=bool)
    first[1:] = (lo[1:] != lo[:-1]) | (hi[1:] != hi[:-1])
    return sp.csr_matrix((w[first], (lo[first], hi[first])), shape=(n, n))

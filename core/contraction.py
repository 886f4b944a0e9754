"""Chain contraction of an undirected graph, for many exact shortest-path queries on one graph.

An experience graph is mostly long chains of degree-2 experiences (odometry links) joined at a few
junctions (loop closures, merges, dead ends). :class:`Chains` (the topology) contracts it once:

* **junctions** are the nodes whose degree (distinct neighbours) is not 2, plus the lowest id of every
  pure cycle (a connected part in which every node has degree 2);
* every other node lies on exactly one **chain**, a path of degree-2 nodes whose two end nodes are
  linked to junctions ``a`` and ``b`` (``a == b`` for a loop that leaves and returns to one junction);
  chains are contiguous slices of one array (``order``), each from its ``a`` end.

:class:`ContractedGraph` adds one weight: the cost of every chain node from its chain's first node
(``cum``, one multi-source Dijkstra along the chains) and the **contracted graph** over the junctions,
with an edge per junction–junction link and per chain between two distinct junctions (cost
``w(a, first) + cum[last] + w(last, b)``), the cheapest of parallel ones kept, and which chain (or
direct link) each edge stands for.

A query starts an A* search over the contracted graph from the source's ways in (its junction, or the two
junctions at its chain's ends at their costs along the chain), guided by two lower bounds of the cost left
to the target: the straight line times the least cost per metre of any link (:func:`cost_per_metre`), and
the triangle inequality through eight landmark junctions whose distances to every junction are computed at
build (:func:`landmark_distances`, ALT). It stops as soon as no junction left in its heap can improve the
best way out to the target (the target's junction, or its chain's end junctions
plus the costs along the chain, and the direct way when both lie on one chain); it then expands the
contracted path into node ids. Every candidate is a path of the original graph and every simple path is
covered by one, so the cost is the exact optimum (to floating-point rounding). The search
(:func:`core._path_kernel.settle`) is compiled by numba and releases the GIL; it reads the graph's
read-only arrays and writes only its own, so any number of threads query one built graph at once without
a lock. Build: a few vectorised csgraph passes and one Dijkstra per landmark, ``O(L log L)`` for ``L``
links; query: ``O(E_r log J_r)`` for the ``J_r`` junctions whose cost plus bound is below the target's (at
most those nearer the source than the target), plus the path. On ``bench/api.py``'s 100,000-experience city
map the bounds cut a query's search about fivefold against plain Dijkstra.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from types import ModuleType
from typing import cast

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra

from core.arrays import BoolArray, FloatArray, Int32Array, IntArray, ScalarT

LANDMARKS = 8  # landmarks of each contracted graph: 8 distances per junction, 8 bounds per settled junction
_Way = tuple[int, float, int]  # (junction index, cost, side): side 0 at a junction, -1 via the a end, +1 via b


@dataclass(frozen=True, slots=True)
class Chains:
    """The chain decomposition of a simple undirected graph on ``n`` nodes (see the module docstring).

    ``chain[x]``: chain of node ``x`` (-1 for junctions); ``order``: chain nodes grouped by chain, each
    chain from its ``a`` end; ``start[c]:start[c + 1]``: chain ``c``'s slice of ``order``; ``position[x]``:
    index of ``x`` in ``order``; ``a``/``b``: junction nodes at each chain's ends; ``first_link``/``last_link``:
    the links (indices into ``lo``/``hi``) joining them; ``inner_links``: links between two chain nodes;
    ``junctions``: junction nodes in increasing order, ``junction_id[x]`` the index of junction ``x`` in it
    (-1 for chain nodes); ``component[x]``: connected component of ``x`` in the whole graph.
    """

    n: int
    chain: IntArray
    order: IntArray
    start: IntArray
    position: IntArray
    a: IntArray
    b: IntArray
    first_link: IntArray
    last_link: IntArray
    inner_links: IntArray
    junctions: IntArray
    junction_id: IntArray
    component: Int32Array

    @classmethod
    def build(cls, n: int, lo: IntArray, hi: IntArray) -> Chains:
        """Decompose the graph of links ``lo[k]``–``hi[k]`` (``lo < hi``, each pair once) into chains."""
        degree = np.bincount(lo, minlength=n) + np.bincount(hi, minlength=n)
        inner = degree == 2
        labels, inner_links = _inner_components(n, lo, hi, inner)
        members = np.flatnonzero(inner)
        # a pure cycle has as many links as nodes: its lowest id becomes a junction
        nodes_per = np.bincount(labels[members], minlength=n)
        links_per = np.bincount(labels[lo[inner_links]], minlength=n)
        cyclic = np.flatnonzero((nodes_per > 0) & (links_per == nodes_per))
        if cyclic.size:
            lowest = np.full(n, n, dtype=np.int64)
            np.minimum.at(lowest, labels[members], members)
            inner[lowest[cyclic]] = False
            labels, inner_links = _inner_components(n, lo, hi, inner)
            members = np.flatnonzero(inner)
        _, chain_of = np.unique(labels[members], return_inverse=True)
        count = int(chain_of.max()) + 1 if members.size else 0
        chain = np.full(n, -1, dtype=np.int64)
        chain[members] = chain_of
        # one end of every chain (a chain node with < 2 chain neighbours) seeds the hop counts along it
        inner_degree = np.bincount(lo[inner_links], minlength=n) + np.bincount(hi[inner_links], minlength=n)
        ends = members[inner_degree[members] < 2]
        _, first = np.unique(chain[ends], return_index=True)
        hops = np.zeros(n)
        if count:
            hops = dijkstra(
                _pattern(n, lo[inner_links], hi[inner_links]), directed=False, indices=ends[first],
                unweighted=True, min_only=True,
            )  # fmt: skip
        order = members[np.lexsort((hops[members], chain_of))]
        start = np.zeros(count + 1, dtype=np.int64)
        start[1:] = np.cumsum(np.bincount(chain_of, minlength=count))
        position = np.full(n, -1, dtype=np.int64)
        position[order] = np.arange(order.size)
        # every chain has exactly two links to junctions: the one at hop 0 joins a, the other one b
        attach = np.flatnonzero(inner[lo] != inner[hi])
        end_node = np.where(inner[lo[attach]], lo[attach], hi[attach])
        junction_end = np.where(inner[lo[attach]], hi[attach], lo[attach])
        ranked = np.lexsort((junction_end, hops[end_node], chain[end_node]))
        attach, junction_end = attach[ranked], junction_end[ranked]
        if not np.array_equal(chain[end_node[ranked]], np.repeat(np.arange(count), 2)):
            msg = "internal error: a chain without exactly two links to junctions"
            raise AssertionError(msg)
        junctions = np.flatnonzero(~inner)
        junction_id = np.full(n, -1, dtype=np.int64)
        junction_id[junctions] = np.arange(junctions.size)
        component = connected_components(_pattern(n, lo, hi), directed=False)[1]
        return cls(
            n=n, chain=chain, order=order, start=start, position=position, a=np.ascontiguousarray(junction_end[0::2]),
            b=np.ascontiguousarray(junction_end[1::2]), first_link=attach[0::2], last_link=attach[1::2],
            inner_links=inner_links,
            junctions=junctions, junction_id=junction_id, component=component,
        )  # fmt: skip


class ContractedGraph:
    """Exact shortest paths on the graph of links ``lo``–``hi`` with costs ``weight`` (all > 0, finite).

    Args:
        chains: the graph's chain decomposition (:meth:`Chains.build` of the same ``lo``, ``hi``).
        lo: first node of each link (``lo < hi``, each pair once).
        hi: second node of each link.
        weight: each link's cost.
    """

    def __init__(
        self, chains: Chains, lo: IntArray, hi: IntArray, weight: FloatArray, points: FloatArray | None = None
    ) -> None:
        self.chains = c = chains
        n, count = c.n, c.start.size - 1
        cum = np.zeros(n)
        if count:
            links = c.inner_links
            along = sp.csr_matrix((weight[links], (lo[links], hi[links])), shape=(n, n))
            cum = dijkstra(along, directed=False, indices=c.order[c.start[:-1]], min_only=True)
            cum[c.chain < 0] = 0.0
        self.cum = _frozen(cum)
        self.length = _frozen(cum[c.order[c.start[1:] - 1]])  # first → last of each chain
        self.to_a, self.to_b = _frozen(weight[c.first_link]), _frozen(weight[c.last_link])
        # contracted edges, both directions: junction–junction links, chains between distinct junctions
        direct = np.flatnonzero((c.junction_id[lo] >= 0) & (c.junction_id[hi] >= 0))
        crossing = np.flatnonzero(c.a != c.b)
        u = np.concatenate([c.junction_id[lo[direct]], c.junction_id[c.a[crossing]]])
        v = np.concatenate([c.junction_id[hi[direct]], c.junction_id[c.b[crossing]]])
        w = np.concatenate([weight[direct], (self.to_a + self.length + self.to_b)[crossing]])
        via = np.concatenate([np.full(direct.size, -1, dtype=np.int64), crossing])
        u, v = np.concatenate([u, v]), np.concatenate([v, u])
        w, via = np.concatenate([w, w]), np.concatenate([via, via])
        ranked = np.lexsort((w, v, u))  # the cheapest of parallel edges comes first
        u, v, w, via = u[ranked], v[ranked], w[ranked], via[ranked]
        keep = np.ones(u.size, dtype=bool)
        keep[1:] = (u[1:] != u[:-1]) | (v[1:] != v[:-1])
        u, v, w, via = u[keep], v[keep], w[keep], via[keep]
        m = c.junctions.size
        self.indptr = _frozen(np.searchsorted(u, np.arange(m + 1)).astype(np.int64))
        self.indices = _frozen(v.astype(np.int64))
        self.data = _frozen(w.astype(np.float64))
        self.keys = _frozen(u * m + v)  # sorted: which entry joins two junctions, and ``via`` what
        self.via = _frozen(via)
        self.points = points
        self.landmarks = _frozen(landmark_distances(self.indptr, self.indices, self.data, LANDMARKS))
        self.scale = cost_per_metre(lo, hi, weight, points)
        self.junction_points = _frozen(np.ascontiguousarray(points[c.junctions, :3], dtype=np.float64)) if (
            self.scale > 0 and points is not None) else _frozen(np.zeros((m, 3)))  # fmt: skip
        _kernel()  # numba's import and the compiled search are loaded with the graph, not on a query

    def search(self, source: int, target: int) -> tuple[float, list[int]] | None:
        """Return (cost, node ids from ``source`` to ``target``) of a shortest path, None when there is none.

        A* from the source's ways in stops once the heap holds no junction whose cost plus bound is below the
        best way out (:func:`core._path_kernel.settle`); the direct way along a shared chain wins a tie with the
        junctions' way.
        """
        c = self.chains
        if source == target:
            return 0.0, [source]
        if c.component[source] != c.component[target]:
            return None
        best = np.inf
        if c.chain[source] >= 0 and c.chain[source] == c.chain[target]:
            best = abs(float(self.cum[target]) - float(self.cum[source]))
        starts = self._ways(source, target)
        ends = self._ways(target, source)
        dist, pred = _kernel().settle(
            self.indptr, self.indices, self.data,
            np.array([s[0] for s in starts], dtype=np.int64), np.array([s[1] for s in starts]),
            np.array([e[0] for e in ends], dtype=np.int64), np.array([e[1] for e in ends]), best,
            self.junction_points, self._goal(target), self.scale, self.landmarks, self._landmark_goal(target),
        )  # fmt: skip
        end = min(ends, key=lambda e: dist[e[0]] + e[1])
        via = float(dist[end[0]]) + end[1]
        if via < best:
            return via, self._expand(source, target, starts, end, pred)
        if np.isfinite(best):
            return best, self._along(source, target)
        return None

    def _goal(self, target: int) -> FloatArray:
        """Return the target's position, the point the search's lower bound measures to (zeros: no bound)."""
        if self.scale > 0 and self.points is not None:
            return np.asarray(self.points[target, :3], dtype=np.float64)
        return np.zeros(3)

    def _landmark_goal(self, target: int) -> FloatArray:
        """Return each landmark's distance to ``target``: through the nearer of its ways in when on a chain."""
        c = self.chains
        chain = int(c.chain[target])
        if chain < 0:
            return np.array(self.landmarks[:, c.junction_id[target]], dtype=np.float64)
        along = float(self.cum[target])
        via_a = self.landmarks[:, c.junction_id[c.a[chain]]] + (float(self.to_a[chain]) + along)
        via_b = self.landmarks[:, c.junction_id[c.b[chain]]] + (
            float(self.length[chain]) - along + float(self.to_b[chain]))  # fmt: skip
        return np.minimum(via_a, via_b)

    def _ways(self, node: int, other: int) -> list[_Way]:
        """Return the ways from ``node`` into the contracted graph: ``(junction index, cost, side)``.

        On a chain shared with ``other`` only the side away from ``other`` is kept (the other one passes it).
        """
        c = self.chains
        chain = int(c.chain[node])
        if chain < 0:
            return [(int(c.junction_id[node]), 0.0, 0)]
        along = float(self.cum[node])
        ways = [
            (int(c.junction_id[c.a[chain]]), float(self.to_a[chain]) + along, -1),
            (int(c.junction_id[c.b[chain]]), float(self.length[chain]) - along + float(self.to_b[chain]), 1),
        ]
        if c.chain[other] == chain:
            return [ways[0]] if c.position[node] < c.position[other] else [ways[1]]
        return ways

    def _along(self, source: int, target: int) -> list[int]:
        """Return the nodes from ``source`` to ``target`` along their shared chain."""
        i, j = int(self.chains.position[source]), int(self.chains.position[target])
        order = self.chains.order
        return cast(list[int], order[i : j + 1].tolist() if i <= j else order[j : i + 1][::-1].tolist())

    def _expand(self, source: int, target: int, starts: list[_Way], end: _Way, pred: IntArray) -> list[int]:
        """Return the node ids of the contracted path to ``end`` (``pred``: −1 at a way in), with the chain ends."""
        c = self.chains
        m = c.junctions.size
        kernel = _kernel()
        junctions = kernel.hops(pred, end[0])
        chains = self.via[np.searchsorted(self.keys, junctions[:-1] * m + junctions[1:])]
        pieces = [kernel.through_chains(c.junctions[junctions], chains, c.order, c.start, c.a)]
        if c.chain[source] >= 0:  # leave the source's chain by the side whose junction the path enters first
            side = min((s for s in starts if s[0] == junctions[0]), key=lambda s: s[1])[2]
            pieces.insert(0, self._to_end(source, side))
        if end[2] != 0:
            pieces.append(self._to_end(target, end[2])[::-1])
        return cast(list[int], np.concatenate(pieces).tolist())

    def _to_end(self, node: int, side: int) -> IntArray:
        """Return the chain nodes from ``node`` to its chain's ``a`` end (side -1) or ``b`` end (+1), inclusive."""
        c = self.chains
        chain, i = int(c.chain[node]), int(c.position[node])
        if side < 0:
            return c.order[c.start[chain] : i + 1][::-1]
        return c.order[i : c.start[chain + 1]]


def landmark_distances(indptr: IntArray, indices: IntArray, data: FloatArray, count: int) -> FloatArray:
    """Return (k, m) distances from ``k ≤ count`` landmarks to every node of the CSR graph (inf: not connected).

    Landmarks are chosen farthest first (Goldberg and Harrelson 2005): the first is the node farthest from
    node 0, each next one the node farthest from those chosen (a node no landmark reaches counts as farthest,
    so that every connected part gets landmarks); ties go to the lowest id.
    """
    m = indptr.size - 1
    if m == 0 or count == 0:
        return np.zeros((0, max(m, 1)))
    graph = sp.csr_matrix((data, indices, indptr), shape=(m, m))
    nearest = dijkstra(graph, directed=True, indices=[0])[0]
    rows: list[FloatArray] = []
    for _ in range(min(count, m)):
        finite = np.isfinite(nearest)
        far = int(np.argmax(~finite)) if not finite.all() else int(np.argmax(nearest))
        row = dijkstra(graph, directed=True, indices=[far])[0]
        rows.append(row)
        nearest = np.minimum(nearest, row) if rows[1:] else row
    return np.ascontiguousarray(np.vstack(rows))


def cost_per_metre(lo: IntArray, hi: IntArray, weight: FloatArray, points: FloatArray | None) -> float:
    """Return a scale ``s`` with ``weight[k] ≥ s · ‖points[lo[k]] − points[hi[k]]‖`` for every link (0: none).

    ``s`` is the least cost per metre of straight line over the links, lowered by one part in 10⁶ for
    rounding. Then every path costs at least ``s`` times the straight line between its ends, so
    ``s · ‖p − p_target‖`` is a consistent lower bound for A* (on the contracted graph too: an edge's cost is
    a path's). No positions, a non-finite one, or a link of zero cost per metre give 0 (plain Dijkstra).
    """
    if points is None or lo.size == 0:
        return 0.0
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    if not np.isfinite(xyz).all():
        return 0.0
    length = np.linalg.norm(xyz[lo] - xyz[hi], axis=1)
    moving = length > 0
    if not moving.any():
        return 0.0
    scale = float(np.min(weight[moving] / length[moving])) * (1.0 - 1e-6)
    return scale if np.isfinite(scale) and scale > 0 else 0.0


def _pattern(n: int, lo: IntArray, hi: IntArray) -> sp.csr_matrix:
    """Return the (n, n) adjacency pattern (ones) of links ``lo``–``hi``."""
    return sp.csr_matrix((np.ones(lo.size), (lo, hi)), shape=(n, n))


def _inner_components(n: int, lo: IntArray, hi: IntArray, inner: BoolArray) -> tuple[Int32Array, IntArray]:
    """Return component labels of the subgraph induced by the ``inner`` nodes, and its links (indices)."""
    links = np.flatnonzero(inner[lo] & inner[hi])
    return connected_components(_pattern(n, lo[links], hi[links]), directed=False)[1], links


def _frozen(array: npt.NDArray[ScalarT]) -> npt.NDArray[ScalarT]:
    """Return ``array`` made read-only: a built graph is shared by concurrent queries and never written."""
    array.setflags(write=False)
    return array


@functools.cache
def _kernel() -> ModuleType:
    """Return :mod:`core._path_kernel`, imported and its functions loaded (:func:`core._path_kernel.load`) once."""
    from core import _path_kernel

    _path_kernel.load()
    return _path_kernel

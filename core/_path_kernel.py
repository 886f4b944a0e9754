"""The compiled search of :mod:`core.contraction`: A* over a CSR graph that stops at its target.

numba compiles the functions below on their first call (``cache=True``: once per machine, then they are
loaded from ``__pycache__``); :func:`load` makes those calls, and :mod:`core.contraction` makes it when it
builds its first graph, so that no query pays for it. The search keeps its
frontier in an indexed binary heap (one entry per node, decreased in place) ordered by (distance, node id),
so equal distances are settled in node order whatever the machine. It only reads the graph's arrays and
releases the GIL (``nogil``): threads query one graph at once.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from core.arrays import FloatArray, IntArray

_DONE = -2  # pos[node] of a settled node; -1: not reached yet
_LANDMARK_MARGIN = 1.0 - 1e-9  # a landmark's bound, lowered for the rounding of its distances


@njit(cache=True, nogil=True)
def _place(key: FloatArray, node: IntArray, pos: IntArray, i: int, d: float, v: int) -> None:
    """Move the hole at heap entry ``i`` towards the root until (``d``, ``v``) fits there, and put it there."""
    while i > 0:
        parent = (i - 1) >> 1
        if key[parent] < d or (key[parent] == d and node[parent] < v):
            break
        key[i] = key[parent]
        node[i] = node[parent]
        pos[node[i]] = i
        i = parent
    key[i] = d
    node[i] = v
    pos[v] = i


@njit(cache=True, nogil=True)
def _offer(key: FloatArray, node: IntArray, pos: IntArray, size: int, v: int, d: float) -> int:
    """Put node ``v`` in the heap at distance ``d``, or lower its entry to ``d``; return the heap's size."""
    i = pos[v]
    if i < 0:
        i = size
        size += 1
    _place(key, node, pos, i, d, v)
    return size


@njit(cache=True, nogil=True)
def _pop(key: FloatArray, node: IntArray, pos: IntArray, size: int) -> int:
    """Remove the first entry (its node is settled) and return the heap's size."""
    pos[node[0]] = _DONE
    size -= 1
    if size == 0:
        return 0
    d, v = key[size], node[size]  # the last entry fills the hole left at the root
    i = 0
    while 2 * i + 1 < size:
        child = 2 * i + 1
        right = child + 1
        if right < size and (key[right] < key[child] or (key[right] == key[child] and node[right] < node[child])):
            child = right
        if d < key[child] or (d == key[child] and v < node[child]):
            break
        key[i] = key[child]
        node[i] = node[child]
        pos[node[i]] = i
        i = child
    key[i] = d
    node[i] = v
    pos[v] = i
    return size


@njit(cache=True, nogil=True)
def settle(
    indptr: IntArray,
    indices: IntArray,
    data: FloatArray,
    start_nodes: IntArray,
    start_costs: FloatArray,
    end_nodes: IntArray,
    end_costs: FloatArray,
    bound: float,
    points: FloatArray,
    goal: FloatArray,
    scale: float,
    landmarks: FloatArray,
    landmark_goal: FloatArray,
) -> tuple[FloatArray, IntArray]:
    """Return (dist, pred) of an A* search over the CSR graph that stops once the target's cost is known.

    The search starts at ``start_nodes`` at ``start_costs`` (``pred`` −1 there unless a cheaper way through
    another node is found) and settles nodes in increasing ``dist + h``, ties by node id, where ``h(v)`` is a
    lower bound of the cost left from ``v`` (A*: Hart, Nilsson and Raphael 1968): the larger of the straight
    line, ``scale · ‖points[v] − goal‖``, and the landmarks' triangle inequality,
    ``max_k |landmark_goal[k] − landmarks[k, v]|`` (ALT: Goldberg and Harrelson 2005; ``landmarks[k]`` holds
    every node's distance from landmark ``k``, ``landmark_goal[k]`` the target's). The caller makes both
    consistent; ``scale`` 0 and no landmarks make the search Dijkstra's. Each settled
    end node ``end_nodes[i]`` lowers the bound to its distance plus ``end_costs[i]``; the search stops when the
    first unsettled node's ``dist + h`` is above the bound (``bound`` starts at the caller's best way that
    avoids the graph, or inf). With a consistent ``h`` every settled node's ``dist`` is exact and its ``pred``
    a shortest way there (up to ties); other nodes hold upper bounds (inf: not reached).
    """
    n = indptr.size - 1
    dist = np.full(n, np.inf)
    pred = np.full(n, -1, dtype=np.int64)
    pos = np.full(n, -1, dtype=np.int64)
    key = np.empty(n, dtype=np.float64)
    node = np.empty(n, dtype=np.int64)
    size = 0
    for i in range(start_nodes.size):
        if start_costs[i] < dist[start_nodes[i]]:
            dist[start_nodes[i]] = start_costs[i]
            left = _left(points, goal, scale, landmarks, landmark_goal, start_nodes[i])
            size = _offer(key, node, pos, size, start_nodes[i], start_costs[i] + left)
    while size > 0 and key[0] <= bound:
        u = node[0]
        d = dist[u]
        size = _pop(key, node, pos, size)
        for i in range(end_nodes.size):
            if end_nodes[i] == u:
                bound = min(bound, d + end_costs[i])
        for k in range(indptr[u], indptr[u + 1]):
            v = indices[k]
            candidate = d + data[k]
            if candidate < dist[v]:  # never true for a settled node: weights are > 0 and h consistent
                dist[v] = candidate
                pred[v] = u
                left = _left(points, goal, scale, landmarks, landmark_goal, v)
                size = _offer(key, node, pos, size, v, candidate + left)
    return dist, pred


@njit(cache=True, nogil=True)
def _left(
    points: FloatArray, goal: FloatArray, scale: float, landmarks: FloatArray, landmark_goal: FloatArray, v: int
) -> float:
    """Return the search's lower bound of the cost from node ``v`` to the goal (see :func:`settle`)."""
    bound = 0.0
    if scale != 0.0:
        dx = points[v, 0] - goal[0]
        dy = points[v, 1] - goal[1]
        dz = points[v, 2] - goal[2]
        bound = scale * np.sqrt(dx * dx + dy * dy + dz * dz)
    for k in range(landmark_goal.size):
        here, there = landmarks[k, v], landmark_goal[k]
        if here < np.inf and there < np.inf:  # a landmark in another component bounds nothing
            bound = max(bound, abs(there - here) * _LANDMARK_MARGIN)
    return bound


@njit(cache=True, nogil=True)
def hops(pred: IntArray, end: int) -> IntArray:
    """Return the nodes of the search's path to ``end``, from its way in (``pred`` −1) to ``end``."""
    count = 1
    node = end
    while pred[node] >= 0:
        node = pred[node]
        count += 1
    out = np.empty(count, dtype=np.int64)
    node = end
    for i in range(count - 1, -1, -1):
        out[i] = node
        node = pred[node]
    return out


@njit(cache=True, nogil=True)
def through_chains(
    nodes: IntArray, chains: IntArray, order: IntArray, start: IntArray, a: IntArray
) -> IntArray:
    """Return the graph nodes of a junction path: ``nodes[k]``, chain ``chains[k]`` (when ≥ 0), ``nodes[k + 1]``, ….

    A chain runs from its ``a`` junction: it is walked forwards when it is left from ``a``, else backwards.
    """
    total = nodes.size
    for k in range(chains.size):
        if chains[k] >= 0:
            total += start[chains[k] + 1] - start[chains[k]]
    out = np.empty(total, dtype=np.int64)
    out[0] = nodes[0]
    i = 1
    for k in range(chains.size):
        chain = chains[k]
        if chain >= 0:
            first, last = start[chain], start[chain + 1]
            forwards = a[chain] == nodes[k]
            for j in range(last - first):
                out[i + j] = order[first + j] if forwards else order[last - 1 - j]
            i += last - first
        out[i] = nodes[k + 1]
        i += 1
    return out


def load() -> None:
    """Compile or load every function above for the argument types :mod:`core.contraction` calls them with.

    The graph's arrays are read-only there (a distinct numba type from writable arrays), the others writable.
    """
    graph = (np.zeros(2, dtype=np.int64), np.zeros(1, dtype=np.int64), np.ones(1))  # one node, one self-link
    for array in graph:
        array.setflags(write=False)
    ends = np.zeros(1, dtype=np.int64)
    points = np.zeros((1, 3))
    points.setflags(write=False)
    landmarks = np.zeros((0, 1))
    landmarks.setflags(write=False)
    _, pred = settle(*graph, ends, np.zeros(1), ends, np.zeros(1), np.inf, points, np.zeros(3), 0.0, landmarks,
                     np.zeros(0))  # fmt: skip
    hops(pred, 0)
    through_chains(ends, ends[:0], ends, ends, ends)

"""Experience-map relaxation: residuals, the bounded per-frame worklist, and the exact fixed point.

OpenRatSLAM's relaxation (Ball et al. 2013; Menezes et al. Eq. 8; PoseidonSLAM thesis
Eq. 4.21 with the incoming-link sign corrected) nudges, for every link l = (i → j)
holding the pose t_l of j in the frame of i, the source by +c·r_l and the target by
−c·r_l, where ``r_l = p_j − (p_i ⊕ t_l)`` and c = ``exp_correction``; the heading
residual is ``wrap(ψ_j − ψ_i − t_ψ)``. Applied to every experience at once with each
experience's summed correction divided by its number of links (OpenRatSLAM applies
the links one after another; the simultaneous form needs the division to stay
stable at c = 0.5 for any degree), one iteration moves experience i by

    Δp_i = c/deg(i) · [ Σ_{l: i = src} r_l − Σ_{l: i = dst} r_l ].

Fixed point. Iterating this over all links until it converges ("full relaxation")
stops where every summed residual vanishes. Those are the normal equations of
min Σ_l ‖r_l‖² (thesis Eq. 4.20 with unit weights): the headings solve a linear
least-squares problem of their own (the heading residual does not involve the
positions), and the positions solve a linear least-squares problem given those
headings. The problems are singular up to a rigid motion of each connected part
of the graph, so each connected component's lowest-id experience is its anchor
and never moves (the first experience stays at the origin of the map frame; a
component built by a merge keeps its lowest id fixed until it is linked). With the
anchors the fixed point is unique (for heading misclosures well under π), so
*any* schedule that keeps relaxing until every correction is tiny — the full
Jacobi sweep, the bounded worklist below, or the direct solve — reaches the same
map. :func:`solve` computes it directly with one sparse factorisation.

Per-frame work. :class:`Worklist` holds the experiences whose correction may still
exceed ``exp_relax_tolerance``: both ends of each new loop-closure or merge link,
an anchor that stopped being one, and the neighbours of every experience moved.
Each frame takes at most ``exp_relax_batch`` of them from its front (widened by
their trajectory neighbours when fewer wait) and moves that block to its own fixed
point with every other experience held still (:func:`solve_block`, one dense
Cholesky solve): a block Gauss–Seidel step, which, like OpenRatSLAM's in-order
link sweeps, carries a correction along a whole stretch of trajectory at once
(simultaneous Jacobi iterations move it one link per iteration). The work per frame
is bounded by a constant whatever the size of the map. An experience leaves the
list when it moves by at most the tolerance, and every experience whose neighbour
moved re-enters it, so an empty list means that every experience's correction is
within the tolerance — a settled map, though not necessarily the exact fixed point
(slowly varying errors on long loops have small corrections); :func:`solve` gives
the exact one at the end of a log.

Parameters. ``exp_correction`` (c) is the step of :meth:`ExperienceMap.relax`'s
full iterations and, per frame, the block moves ``min(1, 2c)`` of the way to its
fixed point (c = 0.5, OpenRatSLAM's value, fully corrects each link it visits, so
it goes all the way). ``exp_loops`` is the number of full iterations
:meth:`ExperienceMap.relax` runs by default; 0 switches relaxation off. Neither
changes the fixed point. ``max_correction_step`` / ``max_correction_norm`` (thesis
§4.2.4) cap how far one iteration / one frame moves an experience: they limit the
speed of relaxation, not where it settles.

Switched subsets. The robust check (:mod:`core.robust`) scores the fixed point over many subsets of one
set of links. :class:`SwitchedRelaxation` computes their residuals without a factorisation each: only
the links of the graph's 2-core (:func:`cycle_links`) can have a residual other than zero, and their
normal matrix over a subset is a low-rank change of one factorised for a reference subset
(Sherman–Morrison–Woodbury). :class:`LinkComponents` tells whether a subset still joins what the whole
graph joins, which the update needs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from scipy.linalg import LinAlgError
from scipy.linalg.lapack import dpotrf, dpotrs
from scipy.sparse.csgraph import breadth_first_order, connected_components
from scipy.sparse.linalg import SuperLU, splu

from core._buffers import GrowBuffer
from core.angles import TWO_PI, wrap_angle_below_pi
from core.arrays import BoolArray, ComplexArray, FloatArray, IndexT, Int32Array, IntArray, SumT


def residuals(pose: FloatArray, src: IntArray, dst: IntArray, transform: FloatArray) -> FloatArray:
    """Return link residuals (K, 4): ``p_dst − (p_src ⊕ t)`` in the map frame, heading wrapped to [−π, π)."""
    source = pose[src]
    out = pose[dst] - source
    cos_y = np.cos(source[:, 3])
    sin_y = np.sin(source[:, 3])
    tx = transform[:, 0]
    ty = transform[:, 1]
    out[:, 0] -= cos_y * tx - sin_y * ty
    out[:, 1] -= sin_y * tx + cos_y * ty
    out[:, 2] -= transform[:, 2]
    out[:, 3] = wrap_angle_below_pi(out[:, 3] - transform[:, 3])
    return out


def roots(parent: npt.NDArray[IndexT]) -> npt.NDArray[IndexT]:
    """Return the union-find root of every node (pointer jumping over a parent array)."""
    root = parent.copy()
    while True:
        nxt = root[root]
        if np.array_equal(nxt, root):
            return root
        root = nxt


def sums_to_root(
    parent: npt.NDArray[IndexT], step: npt.NDArray[SumT]
) -> tuple[npt.NDArray[SumT], npt.NDArray[IndexT]]:
    """Return, for every node of a forest, the sum of ``step`` from it up to its root, and the root.

    ``parent[i]`` is i's parent (a root is its own parent, with step 0); ``step`` is (n,) or (n, k), the
    value of the edge from each node to its parent. Pointer jumping, O(n log depth).
    """
    total = step
    up = parent
    while not np.array_equal(up[up], up):  # invariant: total[i] sums the steps from i up to up[i]
        total = total + total[up]
        up = up[up]
    return total, up


def _movable(n: int, src: IntArray, dst: IntArray, anchor: BoolArray) -> BoolArray | None:
    """Return the mask (n,) of experiences a solve may move: linked and not anchored (None: there are none)."""
    if src.size == 0:
        return None
    linked = np.zeros(n, dtype=bool)
    linked[src] = True
    linked[dst] = True
    free = linked & ~anchor
    return free if free.any() else None


def solve(
    pose: FloatArray, src: IntArray, dst: IntArray, transform: FloatArray, anchor: BoolArray, passes: int = 8
) -> FloatArray:
    """Return the poses at the fixed point of full relaxation (see the module docstring).

    Headings first: with the integer winding of every link taken from the current
    headings, ``min Σ (ψ_dst − ψ_src − t_ψ − 2πk)²`` is a sparse linear system (the
    graph Laplacian over the non-anchored experiences); it is re-solved if a
    winding changes (at most ``passes`` times). Positions then solve the same
    Laplacian with the link translations rotated by the solved source headings.
    Experiences marked ``anchor`` (and experiences without links) keep their pose.
    """
    n = pose.shape[0]
    out = pose.copy()
    free = _movable(n, src, dst, anchor)
    if free is None:
        return out
    k = src.size
    # incidence matrix B (K × n): +1 at the target, −1 at the source
    incidence = sp.csr_matrix(
        (np.concatenate([np.ones(k), -np.ones(k)]), (np.tile(np.arange(k), 2), np.concatenate([dst, src]))),
        shape=(k, n),
    )
    laplacian = (incidence.T @ incidence).tocsr()
    free_idx = np.flatnonzero(free)
    fixed_idx = np.flatnonzero(~free)
    l_ff = laplacian[free_idx][:, free_idx].tocsc()
    l_fa = laplacian[free_idx][:, fixed_idx]
    factor = splu(l_ff)

    def solve_field(measured: FloatArray, fixed_values: FloatArray) -> FloatArray:
        rhs = (incidence.T @ measured)[free_idx] - l_fa @ fixed_values
        return factor.solve(np.ascontiguousarray(rhs))

    yaw = out[:, 3].copy()
    winding = np.round((yaw[dst] - yaw[src] - transform[:, 3]) / TWO_PI)
    for _ in range(max(passes, 1)):
        measured = transform[:, 3] + TWO_PI * winding
        yaw[free_idx] = solve_field(measured, yaw[fixed_idx])
        updated = np.round((yaw[dst] - yaw[src] - transform[:, 3]) / TWO_PI)
        if np.array_equal(updated, winding):
            break
        winding = updated
    cos_y = np.cos(yaw[src])
    sin_y = np.sin(yaw[src])
    measured_xyz = np.stack(
        [
            cos_y * transform[:, 0] - sin_y * transform[:, 1],
            sin_y * transform[:, 0] + cos_y * transform[:, 1],
            transform[:, 2],
        ],
        axis=1,
    )
    out[free_idx, :3] = solve_field(measured_xyz, out[fixed_idx, :3])
    out[free_idx, 3] = wrap_angle_below_pi(yaw[free_idx])
    return out


def solve_block(
    pose: FloatArray,
    ids: IntArray,
    owner: IntArray,
    src: IntArray,
    dst: IntArray,
    transform: FloatArray,
) -> tuple[FloatArray, bool]:
    """Return the fixed point of relaxation for experiences ``ids`` with every other experience held fixed.

    ``ids`` are distinct, non-anchored experiences that each have a link; the links
    touching them are listed grouped by experience (``owner`` = position in ``ids``,
    ``src``/``dst``/``transform`` of each). The block's normal equations — for every
    i in the block, Σ_{l∋i} ±r_l = 0 (module docstring) — are the Dirichlet graph
    Laplacian ``L`` (b × b, positive definite because every block member reaches a
    fixed experience) with the fixed neighbours on the right-hand side; headings are
    solved first (windings from the current headings), then positions for the new
    headings, with one Cholesky factorisation. Returns the new (b, 4) poses and
    whether any link's heading winding changed (then the result is only approximate).
    """
    b = ids.size
    is_source = src == ids[owner]
    other = np.where(is_source, dst, src)
    sign = np.where(is_source, 1.0, -1.0)
    order = np.argsort(ids)
    slot = np.minimum(np.searchsorted(ids, other, sorter=order), b - 1)
    local = order[slot]
    inside = ids[local] == other
    degree = np.bincount(owner, minlength=b).astype(np.float64)
    starts = np.concatenate([[0], np.cumsum(degree[:-1])]).astype(np.int64)
    flat = owner[inside] * b + local[inside]
    laplacian = np.diag(degree) - np.bincount(flat, minlength=b * b).reshape(b, b)
    factor = _cholesky(laplacian)

    yaw = pose[:, 3]
    raw = yaw[dst] - yaw[src] - transform[:, 3]
    winding = np.round(raw / TWO_PI)
    measured = transform[:, 3] + TWO_PI * winding
    fixed_yaw = np.where(inside, 0.0, yaw[other])
    new_yaw = _cho_solve(factor, np.add.reduceat(fixed_yaw - sign * measured, starts))

    other_yaw = np.where(inside, new_yaw[local], yaw[other])
    source_yaw = np.where(is_source, new_yaw[owner], other_yaw)
    target_yaw = np.where(is_source, other_yaw, new_yaw[owner])
    changed = bool(np.any(np.round((target_yaw - source_yaw - transform[:, 3]) / TWO_PI) != winding))
    cos_y, sin_y = np.cos(source_yaw), np.sin(source_yaw)
    measured_xyz = np.empty((src.size, 3))
    measured_xyz[:, 0] = cos_y * transform[:, 0] - sin_y * transform[:, 1]
    measured_xyz[:, 1] = sin_y * transform[:, 0] + cos_y * transform[:, 1]
    measured_xyz[:, 2] = transform[:, 2]
    fixed_xyz = pose[other, :3] * (~inside)[:, None]
    new_xyz = _cho_solve(factor, np.add.reduceat(fixed_xyz - sign[:, None] * measured_xyz, starts))
    out = np.empty((b, 4))
    out[:, :3] = new_xyz
    out[:, 3] = new_yaw
    return out, changed


def sorted_unique(ids: IntArray) -> IntArray:
    """Return the distinct values of an integer array in increasing order (``np.unique`` without its overhead)."""
    ordered = np.sort(ids)
    if ordered.size < 2:
        return ordered
    keep = np.empty(ordered.size, dtype=bool)
    keep[0] = True
    np.not_equal(ordered[1:], ordered[:-1], out=keep[1:])
    return ordered[keep]


def member_of(values: IntArray, sorted_set: IntArray) -> BoolArray:
    """Return a mask: is each of ``values`` in ``sorted_set`` (increasing, non-empty)? ``np.isin`` by bisection."""
    slot = np.minimum(np.searchsorted(sorted_set, values), sorted_set.size - 1)
    return cast(BoolArray, sorted_set[slot] == values)


def _cholesky(matrix: FloatArray) -> FloatArray:
    """Return the lower Cholesky factor of a symmetric positive definite matrix (LAPACK ``dpotrf``).

    The LAPACK routine scipy's ``cho_factor`` wraps, called directly: on the
    relaxation's small blocks the wrapper's checks cost more than the factorisation.
    """
    factor, info = dpotrf(matrix, lower=1, clean=0)
    if info != 0:
        msg = f"relaxation block is not positive definite (dpotrf info {info})"
        raise LinAlgError(msg)
    return cast(FloatArray, factor)


def _cho_solve(factor: FloatArray, rhs: FloatArray) -> FloatArray:
    """Solve ``L·Lᵀ·x = rhs`` for the lower factor of :func:`_cholesky` (LAPACK ``dpotrs``)."""
    solution, info = dpotrs(factor, rhs, lower=1)
    if info != 0:
        msg = f"dpotrs failed (info {info})"
        raise LinAlgError(msg)
    return cast(FloatArray, solution)


class PairSet:
    """The ordered (source, target) pairs of a map's links, for the check that a link is not added twice.

    The pairs a map is restored with are one sorted int64 array of keys ``source · 2³² + target`` (ids
    0 ≤ id < 2³¹), those added later a set of keys: a restored map of 200,000 links holds 1.6 MB for them,
    a set of tuples ~32 MB.
    """

    def __init__(self, source: IntArray | None = None, target: IntArray | None = None) -> None:
        keys = np.zeros(0, dtype=np.int64) if source is None or target is None else self.keys(source, target)
        self._sorted = np.sort(keys)
        self._added: set[int] = set()

    @staticmethod
    def keys(source: IntArray, target: IntArray) -> IntArray:
        """Return the key of every pair (source[i], target[i])."""
        return (np.asarray(source, dtype=np.int64) << 32) | np.asarray(target, dtype=np.int64)

    def __contains__(self, pair: tuple[int, int]) -> bool:
        key = (int(pair[0]) << 32) | int(pair[1])
        if key in self._added:
            return True
        at = int(np.searchsorted(self._sorted, key))
        return at < self._sorted.size and int(self._sorted[at]) == key

    def add(self, source: int, target: int) -> None:
        """Record the pair (source, target)."""
        self._added.add((int(source) << 32) | int(target))


class Incidence:
    """The links touching each experience, as a padded (E, W) int32 table (−1: none); W doubles when a row fills."""

    def __init__(self, capacity: int = 64, width: int = 4) -> None:
        self._table = np.full((max(capacity, 1), width), -1, dtype=np.int32)
        self._degree = np.zeros(max(capacity, 1), dtype=np.int64)
        self._n = 0

    @property
    def degree(self) -> IntArray:
        """Return the number of links of every experience (view)."""
        return self._degree[: self._n]

    def add_nodes(self, count: int) -> None:
        """Append ``count`` experiences without links."""
        need = self._n + count
        if need > self._table.shape[0]:
            capacity = max(need, 2 * self._table.shape[0])
            table = np.full((capacity, self._table.shape[1]), -1, dtype=np.int32)
            table[: self._n] = self._table[: self._n]
            degree = np.zeros(capacity, dtype=np.int64)
            degree[: self._n] = self._degree[: self._n]
            self._table, self._degree = table, degree
        self._n = need

    def add_link(self, a: int, b: int, link: int) -> None:
        """Record link ``link`` at both of its ends."""
        for node in (a, b):
            slot = int(self._degree[node])
            if slot >= self._table.shape[1]:
                wider = np.full((self._table.shape[0], 2 * self._table.shape[1]), -1, dtype=np.int32)
                wider[:, : self._table.shape[1]] = self._table
                self._table = wider
            self._table[node, slot] = link
            self._degree[node] = slot + 1

    def gather(self, ids: IntArray) -> tuple[Int32Array, IntArray]:
        """Return (links, owner): the links (int32) of ``ids`` by experience, and each one's place in ``ids``."""
        width = int(self._degree[ids].max()) if ids.size else 0
        rows = self._table[:, :width][ids]
        mask = rows >= 0
        owner = np.nonzero(mask)[0]
        return rows[mask], owner

    @classmethod
    def from_links(cls, n: int, src: IntArray, dst: IntArray) -> Incidence:
        """Build the table of ``n`` experiences from link endpoints (links listed in id order at each end)."""
        k = src.size
        ends = np.concatenate([src, dst]).astype(np.int64, copy=False)
        links = np.tile(np.arange(k, dtype=np.int32), 2)
        order = np.lexsort((links, ends))
        ends, links = ends[order], links[order]
        degree = np.bincount(ends, minlength=n).astype(np.int64)
        width = 4
        while width < (int(degree.max()) if degree.size else 0):
            width *= 2
        table = cls(capacity=max(n, 64), width=width)
        table.add_nodes(n)
        first = np.concatenate([[0], np.cumsum(degree)[:-1]]) if n else np.zeros(0, dtype=np.int64)
        slot = np.arange(ends.size) - first[ends]
        table._table[ends, slot] = links
        table._degree[:n] = degree
        return table


class Worklist:
    """A first-in first-out queue of experience ids without duplicates."""

    def __init__(self) -> None:
        self._items = GrowBuffer((), np.int64)
        self._head = 0
        self._queued = np.zeros(64, dtype=bool)

    def __len__(self) -> int:
        return len(self._items) - self._head

    def reserve(self, n: int) -> None:
        """Make room for experience ids below ``n``."""
        if n > self._queued.shape[0]:
            grown = np.zeros(max(n, 2 * self._queued.shape[0]), dtype=bool)
            grown[: self._queued.shape[0]] = self._queued
            self._queued = grown

    def push(self, ids: IntArray) -> None:
        """Append the ids not queued yet (each once, in increasing order)."""
        if ids.size == 0:
            return
        ids = sorted_unique(ids)
        self.reserve(int(ids[-1]) + 1)
        new = ids[~self._queued[ids]]
        if new.size:
            self._queued[new] = True
            self._items.extend(new)

    def extend_ordered(self, ids: IntArray) -> None:
        """Append distinct ids in the given order (restoring a saved queue)."""
        ids = np.asarray(ids, dtype=np.int64)
        if ids.size == 0:
            return
        self.reserve(int(ids.max()) + 1)
        new = ids[~self._queued[ids]]
        self._queued[new] = True
        self._items.extend(new)

    def pop(self, count: int) -> IntArray:
        """Remove and return up to ``count`` ids from the front."""
        stop = min(self._head + count, len(self._items))
        out = self._items.view[self._head : stop].copy()
        self._head = stop
        self._queued[out] = False
        if self._head == len(self._items):
            self._items = GrowBuffer((), np.int64)
            self._head = 0
        elif self._head > 4096 and 2 * self._head > len(self._items):
            self._items = GrowBuffer.from_array(self._items.view[self._head :], np.int64)
            self._head = 0
        return out

    def items(self) -> IntArray:
        """Return the queued ids in order (a copy)."""
        return self._items.view[self._head :].copy()

    def clear(self) -> None:
        """Empty the queue."""
        self._queued[self.items()] = False
        self._items = GrowBuffer((), np.int64)
        self._head = 0


def length_weights(distance: FloatArray, length: float) -> FloatArray:
    """Return each link's weight in :func:`refine_jointly`: ``√(s / max(d, s))`` for a link of ``d`` metres.

    Odometry's error grows with the distance driven (its variance about linearly), so a link that
    spans more than one experience spacing ``s`` — a reckoning link over a long relocalised stretch,
    tens of metres of the robot's own dead reckoning — is trusted as that many links in a row, not as
    one (measured: ``twin-overlap`` turns alike 40 m seed 6's single route, a 66.9 m reckoning link
    9.4 m and 38° off the truth bent the joint optimum to 4.36 m APE).
    """
    d = np.asarray(distance, dtype=np.float64)
    return np.sqrt(length / np.maximum(d, length)) if length > 0 else np.ones(d.shape)


def refine_jointly(
    pose: FloatArray,
    src: IntArray,
    dst: IntArray,
    transform: FloatArray,
    anchor: BoolArray,
    heading_weight: float = 1.0,
    iterations: int = 3,
    weight: FloatArray | None = None,
) -> FloatArray:
    """Return ``pose`` moved by Gauss–Newton steps on the joint least squares over positions and headings.

    Minimises ``Σ_l w_l²·(‖r_l,xyz‖² + (heading_weight · r_l,ψ)²)`` (``weight`` w, 1 when None; see
    :func:`length_weights`) with r from :func:`residuals` (Grisetti et al., "A Tutorial on Graph-Based
    SLAM", 2010, Eqs. 22–30, over SE(2) × z), from ``pose`` (normally
    :func:`solve`'s fixed point). OpenRatSLAM's fixed point solves the headings from the heading
    residuals alone, so a loop whose closures carry heading errors (a forward view matched a few degrees
    round) keeps them and misses in position by that error times the loop's lever arm; here the position
    residuals turn the headings too. Experiences marked ``anchor`` and experiences without links keep their
    pose; the linearisation is about each step's headings.
    """
    n = pose.shape[0]
    out = pose.copy()
    free = _movable(n, src, dst, anchor)
    if free is None:
        return out
    column = np.full(n, -1, dtype=np.int64)
    column[free] = np.arange(int(np.count_nonzero(free)))
    k = src.size
    rows = np.arange(4 * k).reshape(k, 4)
    w = np.ones(k) if weight is None else np.asarray(weight, dtype=np.float64)
    for _ in range(iterations):
        r = residuals(out, src, dst, transform)
        r[:, 3] *= heading_weight
        r *= w[:, None]
        cos_y, sin_y = np.cos(out[src, 3]), np.sin(out[src, 3])
        tx, ty = transform[:, 0], transform[:, 1]
        # ∂r/∂(x, y, z, ψ) of the target: I (heading weighted); of the source: −I, and r_xy turns with ψ_src
        entries = [
            (rows[:, a], dst, a, w * (1.0 if a < 3 else heading_weight)) for a in range(4)
        ] + [
            (rows[:, a], src, a, -w * (1.0 if a < 3 else heading_weight)) for a in range(4)
        ] + [
            (rows[:, 0], src, 3, w * (sin_y * tx + cos_y * ty)),
            (rows[:, 1], src, 3, w * (-cos_y * tx + sin_y * ty)),
        ]  # fmt: skip
        data, row_idx, col_idx = [], [], []
        for row, node, axis, value in entries:
            keep = column[node] >= 0
            data.append(value[keep])
            row_idx.append(row[keep])
            col_idx.append(4 * column[node[keep]] + axis)
        jac = sp.csr_matrix(
            (np.concatenate(data), (np.concatenate(row_idx), np.concatenate(col_idx))),
            shape=(4 * k, 4 * int(np.count_nonzero(free))),
        )
        normal = (jac.T @ jac).tocsc()
        try:
            step = splu(normal).solve(-(jac.T @ r.reshape(-1)))
        except RuntimeError:  # singular: a free experience whose variables no link constrains
            break
        out[free] += step.reshape(-1, 4)
        if float(np.max(np.abs(step))) < 1e-9:
            break
    out[free, 3] = wrap_angle_below_pi(out[free, 3])
    return out


def subtree_sums(parent: npt.NDArray[IndexT], value: FloatArray) -> FloatArray:
    """Return, for every node of a forest, the sum of ``value`` over its subtree (itself and its descendants).

    ``parent[i]`` is i's parent (a root is its own parent). Doubling: with ``T_k(v)`` the sum over the
    descendants less than ``2^k`` links below v, ``T_{k+1}(v) = T_k(v) + Σ_{w: 2^k-th ancestor of w is v} T_k(w)``;
    O(n log depth), no loop over nodes.
    """
    n = parent.size
    depth, _ = sums_to_root(parent, (parent != np.arange(n)).astype(np.int64))
    total = np.asarray(value, dtype=np.float64).copy()
    up, reach = parent.copy(), 1
    while n and reach <= int(depth.max()):
        below = depth >= reach  # w with a 2^k-th ancestor
        total = total + np.bincount(up[below], weights=total[below], minlength=n)
        up, reach = up[up], 2 * reach
    return total


def cycle_links(n: int, src: IntArray, dst: IntArray) -> BoolArray:
    """Return a mask (K,) of the links in the 2-core of the graph: on a cycle, or on a path between two cycles.

    The rest are trees hanging from it (or joining an anchor to it), whose links every least-squares
    solution satisfies exactly. Over a spanning forest (breadth first), the 2-core is the links outside the
    forest and the forest links on the paths between their ends: the link from v to its parent is one when
    v's subtree holds some but not all of its tree's ends of non-forest links (:func:`subtree_sums`).
    """
    k = src.size
    out = np.zeros(k, dtype=bool)
    if k == 0:
        return out
    _, labels = connected_components(sp.csr_matrix((np.ones(k), (src, dst)), shape=(n, n)), directed=False)
    first = np.full(int(labels.max()) + 1, n, dtype=np.int64)
    np.minimum.at(first, labels, np.arange(n, dtype=np.int64))
    # one breadth-first forest: a virtual node n joined to each component's lowest node
    rows = np.concatenate([src, first])
    cols = np.concatenate([dst, np.full(first.size, n)])
    graph = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n + 1, n + 1))
    _, pred = breadth_first_order(graph, n, directed=False, return_predecessors=True)
    parent = pred[:n].copy()
    top = parent == n
    parent[top] = np.flatnonzero(top)  # each component's lowest node is its tree's root
    child = np.flatnonzero(parent != np.arange(n))
    lo, hi = np.minimum(src, dst), np.maximum(src, dst)
    key = lo * n + hi
    order = np.argsort(key, kind="stable")
    tree = order[np.searchsorted(key[order], np.minimum(child, parent[child]) * n + np.maximum(child, parent[child]))]
    out[:] = True
    out[tree] = False  # the non-forest links
    ends = np.bincount(np.concatenate([src[out], dst[out]]), minlength=n).astype(np.float64)
    below = subtree_sums(parent, ends)
    total = below[roots(parent)]
    out[tree] = (below[child] > 0) & (below[child] < total[child])
    return out


#: a normalised residual above which a link is taken to lie on a cycle of the links solved over: a bridge's is zero
#: but for rounding, below 1e-9 on the bench's maps
ON_A_CYCLE = 1e-3


class LinkComponents:
    """The connected parts of a graph whose links other than ``fixed`` ones may be switched off.

    The fixed links are contracted once (``node``: each experience's part of the fixed graph); the parts over a
    set of switches are those of the contracted graph over the switched links that are on, kept as both
    directions of each link sorted by their first end, so that a set's graph is a mask of one array.
    """

    def __init__(self, n: int, src: IntArray, dst: IntArray, fixed: BoolArray) -> None:
        fixed = np.asarray(fixed, dtype=bool)
        on = np.flatnonzero(fixed)
        self.size, self.node = connected_components(
            sp.csr_matrix((np.ones(on.size), (src[on], dst[on])), shape=(n, n)), directed=False
        )
        self.fixed = on
        self.switched = np.flatnonzero(~fixed)
        a, b = self.node[src[self.switched]], self.node[dst[self.switched]]
        first, second = np.concatenate([a, b]), np.concatenate([b, a])
        order = np.argsort(first, kind="stable")
        self._first, self._second = first[order], second[order].astype(np.int32)
        self._link = np.tile(self.switched, 2)[order]  # the link of each direction
        every = self.labels(np.ones(src.size, dtype=bool))
        assert every is not None  # every link on, the fixed ones too
        self.parts = int(np.max(every, initial=-1)) + 1  # the whole graph's
        self._known: dict[bytes, bool] = {}  # the last sets tested

    def labels(self, active: BoolArray) -> Int32Array | None:
        """Return each fixed part's component over ``active`` (None when a fixed link is off)."""
        if not active[self.fixed].all():
            return None
        on = active[self._link]
        indptr = np.zeros(self.size + 1, dtype=np.int32)
        np.cumsum(np.bincount(self._first[on], minlength=self.size), out=indptr[1:])
        indices = self._second[on]
        graph = sp.csr_matrix((np.ones(indices.size), indices, indptr), shape=(self.size, self.size))
        return connected_components(graph, directed=True, connection="weak")[1]

    def whole(self, active: BoolArray, known: tuple[BoolArray, FloatArray] | None = None) -> bool:
        """Return whether ``active`` joins every part the whole graph joins.

        ``known``: a set of switches found whole and its links' residuals ``z`` at the least-squares fixed point
        over it. A link whose residual is not zero there lies on a cycle of it (a bridge's residual is zero: nothing
        else pulls on it), so that set less that one link, with any links added, is whole too, and no count is
        needed. Otherwise the parts are counted (the last sets tested are kept).
        """
        key = active.tobytes()
        found = self._known.get(key)
        if found is None and known is not None and self._known.get(known[0].tobytes()):
            removed = np.flatnonzero(known[0] & ~active)
            found = True if removed.size == 0 or (removed.size == 1 and known[1][removed[0]] > ON_A_CYCLE) else None
        if found is None:
            labels = self.labels(active)
            found = labels is not None and int(np.max(labels, initial=-1)) + 1 == self.parts
        self._remember(key, found)
        return found

    def remember(self, active: BoolArray) -> None:
        """Record that ``active`` is whole (a set Kruskal's rule has just joined)."""
        self._remember(active.tobytes(), True)

    def _remember(self, key: bytes, found: bool) -> None:
        if key not in self._known and len(self._known) >= 64:
            self._known.pop(next(iter(self._known)))
        self._known[key] = found


#: links of the 2-core from which :meth:`SwitchedRelaxation.run_sums` takes the compiled loop (the same bits either
#: way): below it numba's import and the kernel's load (≈ 0.3 s the first time in a process) outweigh what it saves
COMPILED_FROM = 256


class SwitchedRelaxation:
    """The relaxation's fixed point over subsets of one set of links, by low-rank updates of one factorisation.

    Computes the link residuals of :func:`solve` (``passes=1``: windings from ``pose``'s headings, fixed per
    link) over any subset ``A`` of the links that keeps the graph's parts whole, for the links whose residual
    can be other than zero: those of the 2-core (:func:`cycle_links`). The trees hanging from it move rigidly
    with their root and their links fit exactly; and a part with one anchor has residuals that a rigid motion
    of the part leaves as they are (headings shift, positions turn), so each part of the 2-core is solved with
    its lowest experience held at the origin (its *gauge*) instead of its anchor.

    Chains. A run of fixed links through experiences with no other link (:func:`_chains`) takes, at the least
    squares, the same residual on each of its m links, 1/m of the run's misclosure: the equations of its inner
    experiences eliminated (Kron reduction), it is one link of weight 1/m between the experiences at its ends
    (*terminals*) that measures the run's sum. Headings: the sum of the links' (windings taken). Positions: the
    sum of each link's translation turned by its source's heading, which lies on the run at ``ψ_a + P + (k/m)·e``
    (P the headings measured from the start ``a``, k links along, e the run's heading misclosure).

    Over the free terminals the normal matrix is ``L_A = Bᵀ_A W B_A`` (B: incidence, +1 at the target, −1 at the
    source; W the runs' weights). It is factorised once for a reference set R; for A, with D the switched links
    on in exactly one of the two and ``S = diag(±1)`` (+1: on in A), ``L_A = L_R + B_D S B_Dᵀ`` and by the
    Sherman–Morrison–Woodbury identity (Golub & Van Loan, *Matrix Computations*, 4th ed., §2.1.4)

        L_A⁻¹ b = L_R⁻¹ b − W_D (S + B_Dᵀ W_D)⁻¹ B_Dᵀ L_R⁻¹ b,   W_D = L_R⁻¹ B_D,

    one solve with R's factor per right-hand side plus a |D| × |D| system; the columns of W are solved once
    per reference and kept. When |D| exceeds ``REBASE`` the reference moves to A (a new factorisation).
    Headings and heights first (right-hand sides linear in the switches), then positions for those headings.
    The residuals equal :func:`solve`'s up to rounding (tests/core/test_relaxation.py compares them on random graphs).
    """

    #: links in D beyond which the reference is factorised afresh at A. Measured on the bench's robust checks
    #: (time per state scored): 16-24 the least, 8 and 48 1.2-1.7 times that (more factorisations; wider updates).
    REBASE = 24

    def __init__(
        self, pose: FloatArray, src: IntArray, dst: IntArray, transform: FloatArray, anchor: BoolArray,
        parts: LinkComponents,
    ) -> None:  # fmt: skip
        n = pose.shape[0]
        self.parts = parts  # the graph's parts over the links that may be switched off
        self.usable = _one_anchor_each(n, src, dst, anchor) and not np.any(src == dst)
        self.links = np.flatnonzero(cycle_links(n, src, dst)) if self.usable else np.zeros(0, np.int64)
        switched = np.zeros(src.size, dtype=bool)
        switched[parts.switched] = True
        yaw = pose[:, 3]
        winding = np.round((yaw[dst] - yaw[src] - transform[:, 3]) / TWO_PI)  # as solve() takes them
        t = transform[self.links]
        heading = t[:, 3] + TWO_PI * winding[self.links]
        runs = _chains(n, src[self.links], dst[self.links], switched[self.links], heading)
        self.run, self.offset, self.along, self.sign = runs.run, runs.offset, runs.along, runs.sign
        self.switched = runs.switched  # the runs that are one switched link, and that link's position in ``links``
        self.length = runs.length.astype(np.float64)
        self.turned = self.sign * (t[:, 0] + 1j * t[:, 1])  # each link's translation, along its run
        self.member = sp.csr_matrix((np.ones(self.links.size), (self.run, np.arange(self.links.size))),
                                    shape=(runs.length.size, self.links.size)).astype(np.complex128)  # fmt: skip
        rise = np.bincount(self.run, weights=self.sign * t[:, 2], minlength=runs.length.size)
        self.linear = np.stack([runs.heading, rise])  # what each run measures of the fields linear in the switches
        self.flat = not np.any(t[:, 2])  # no climb: the heights stay 0
        self.local_src, self.local_dst, self.free = _local_indices(runs.start, runs.end)
        nf, kr = self.free, runs.length.size
        rows = np.concatenate([self.local_dst, self.local_src])
        keep = rows < nf  # a gauge's row is dropped: it is held at the origin
        values = np.concatenate([np.ones(kr), -np.ones(kr)])[keep]
        self.incidence_t = sp.csr_matrix((values, (rows[keep], np.tile(np.arange(kr), 2)[keep])), shape=(nf, kr))
        self._incidence_c = self.incidence_t.astype(np.complex128)
        self._incidence_csr = _csr_arrays(self.incidence_t)
        self._member_csr = _csr_arrays(self.member)
        self._link_terms = (self.offset, self.along, np.ascontiguousarray(self.turned.real),
                            np.ascontiguousarray(self.turned.imag))  # fmt: skip
        self.weight = 1.0 / np.maximum(self.length, 1.0)
        self._reference = np.zeros(self.switched[0].size, dtype=bool)
        self._factor: SuperLU | None = None
        self._fields = np.zeros((2, nf + 1))
        self._slot = np.full(kr, -1, dtype=np.int64)
        self._columns = np.zeros((0, nf + 1))
        self._filled = 0

    def residuals(self, active: BoolArray) -> tuple[FloatArray, FloatArray] | None:
        """Return the 2-core's links' residuals at the fixed point over ``active``: translation norms and headings.

        The heading residuals are wrapped to [−π, π) as :func:`residuals` wraps them. None when ``active`` splits
        a part of the graph (or turns a fixed link off): :func:`solve` then holds the experiences cut off still,
        which the update does not model. Each link takes its run's (:meth:`run_residuals`), the heading signed
        along the link.
        """
        found = self.run_residuals(active)
        if found is None:
            return None
        return found[0][self.run], self.sign * found[1][self.run]

    def run_residuals(self, active: BoolArray) -> tuple[FloatArray, FloatArray] | None:
        """Return each run's per-link residuals at the fixed point over ``active``: translation norms and headings.

        Every link of a run takes the same residual, 1/m of the run's misclosure: the translation norm, and the
        heading signed along the run (a link pointing against its run takes its negative). None as
        :meth:`residuals`.
        """
        if not self.usable or not self.parts.whole(active):
            return None
        changed = active[self.links[self.switched[1]]]
        d = np.flatnonzero(changed != self._reference)
        if self._factor is None or d.size > self.REBASE:
            self._rebase(changed)
            d = d[:0]
        on = np.ones(self.length.size)
        on[self.switched[0]] = changed
        fields = self._fields  # headings and heights at the terminals: L_A⁻¹ Bᵀ_A W m
        runs = self.switched[0][d]
        update = None
        if d.size:
            columns = self._solved_columns(runs)
            ends = self.local_src[runs], self.local_dst[runs]
            sign = np.where(changed[d], 1.0, -1.0)
            inverse = np.linalg.inv(np.diag(sign) + columns[:, ends[1]].T - columns[:, ends[0]].T)  # the capacitance's
            update = columns, ends, cast(FloatArray, inverse)
            fields = self.low_rank(fields, self.linear[:, runs] * sign, update)
        src, dst = self.local_src, self.local_dst
        miss, planar, rhs = self.run_sums(fields, on * self.weight)
        assert self._factor is not None  # made by _rebase
        solved = self._factor.solve(rhs)
        xy = self.low_rank(solved, None, update)
        distance = np.abs(xy[dst] - xy[src] - planar)
        if not self.flat:
            distance = np.hypot(distance, miss[1])
        turn = miss[0] / self.length  # each link of a run takes 1/m of its misclosure
        wrap = np.abs(turn) > math.pi
        if wrap.any():
            turn[wrap] = wrap_angle_below_pi(turn[wrap])
        return distance / self.length, turn

    def low_rank(
        self, values: FloatArray, measured: FloatArray | None,
        update: tuple[FloatArray, tuple[IntArray, IntArray], FloatArray] | None,
    ) -> np.ndarray:  # fmt: skip
        """Return R's solution ``values`` moved to A's by the Woodbury identity (class docstring).

        ``update``: ``W_D`` (the changed runs' solved columns), their terminals and the capacitance's inverse;
        None when A is R. ``measured`` (2, D): the fields' case, ``values`` R's headings and heights (2, free + 1);
        None: the positions' case, ``values`` R's solve (free, 2), returned complex (free + 1,). Each product is
        summed over D in order from its first term: by the compiled loops from ``COMPILED_FROM`` links of the
        2-core on (:mod:`core._switched_kernel`), else by :func:`_sequential` (the same bits).
        """
        if measured is None and update is None:
            xy = np.zeros(self.free + 1, dtype=np.complex128)
            xy.real[: self.free] = values[:, 0]
            xy.imag[: self.free] = values[:, 1]
            return xy
        if update is None:
            return values
        columns, ends, inverse = update
        if self.links.size >= COMPILED_FROM:
            from core._switched_kernel import low_rank_fields, low_rank_positions

            if measured is None:
                return low_rank_positions(values, columns, ends, inverse)
            return low_rank_fields(values, measured, columns, ends, inverse)
        if measured is None:
            planes = np.zeros((self.free + 1, 2))
            planes[: self.free] = values
            across = planes.T
            across = across - _sequential(_sequential(inverse, (across[:, ends[1]] - across[:, ends[0]]).T).T, columns)
            return np.ascontiguousarray(across.T).view(np.complex128).ravel()
        values = values + _sequential(measured, columns)
        return values - _sequential(_sequential(values[:, ends[1]] - values[:, ends[0]], inverse.T), columns)

    def run_sums(self, fields: FloatArray, weight: FloatArray) -> tuple[FloatArray, ComplexArray, FloatArray]:
        """Return each run's misclosure (2, R), what it measures in the plane (R,) and the position solve's rhs.

        ``fields``: the headings and heights at the terminals; ``weight``: each run's weight, 0 where it is off.
        Each link's translation is turned by its source's heading on its run, ``ψ_a + P + (k/m)·e``, and summed
        per run (``planar``); the right-hand side is ``Bᵀ_A W planar`` (free, 2: real, imaginary). From
        ``COMPILED_FROM`` links of the 2-core on, by the compiled loop (:mod:`core._switched_kernel`, the same
        bits as the numpy expressions of :meth:`run_sums_numpy`).
        """
        if self.links.size < COMPILED_FROM:
            return self.run_sums_numpy(fields, weight)
        from core._switched_kernel import run_sums

        return run_sums(fields, self.linear, (self.local_src, self.local_dst), self._link_terms, self._member_csr,
                        weight, self._incidence_csr)  # fmt: skip

    def run_sums_numpy(self, fields: FloatArray, weight: FloatArray) -> tuple[FloatArray, ComplexArray, FloatArray]:
        """Return :meth:`run_sums` by whole-array numpy passes (the reference of the compiled loop)."""
        src, dst = self.local_src, self.local_dst
        miss = fields[:, dst] - fields[:, src] - self.linear  # each run's misclosure: headings, heights
        source = fields[0, src][self.run] + self.offset + self.along * miss[0, self.run]  # each link's source
        turned = np.empty(source.size, dtype=np.complex128)
        np.cos(source, out=turned.real)
        np.sin(source, out=turned.imag)
        planar = np.asarray(self.member @ (turned * self.turned))  # what each run measures in the plane
        rhs = np.asarray(self._incidence_c @ (planar * weight))
        return miss, planar, rhs.view(np.float64).reshape(-1, 2)

    def _rebase(self, changed: BoolArray) -> None:
        """Factorise the normal matrix over the runs with the switched links ``changed`` on: the new reference."""
        on = np.ones(self.length.size)
        on[self.switched[0]] = changed
        weight = sp.diags(on * self.weight)
        normal = (self.incidence_t @ weight @ self.incidence_t.T).tocsc()
        self._factor = splu(normal, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                            options={"SymmetricMode": True})  # fmt: skip
        self._fields = np.zeros((2, self.free + 1))
        rhs = np.ascontiguousarray(self.incidence_t @ (self.linear * (on * self.weight)).T)
        self._fields[:, : self.free] = self._factor.solve(rhs).T
        self._reference = changed.copy()
        self._slot[:] = -1
        self._filled = 0

    def _solved_columns(self, runs: IntArray) -> FloatArray:
        """Return ``W_D`` as rows (|D|, free + 1; the gauge's entry 0): ``L_R⁻¹ b_r`` of each run, solved once."""
        missing = runs[self._slot[runs] < 0]
        if missing.size:
            need = self._filled + missing.size
            if need > self._columns.shape[0]:
                grown = np.zeros((max(need, 2 * self._columns.shape[0], 8), self.free + 1))
                grown[: self._filled] = self._columns[: self._filled]
                self._columns = grown
            rhs = np.zeros((self.free + 1, missing.size))
            which = np.arange(missing.size)
            rhs[self.local_dst[missing], which] = 1.0
            rhs[self.local_src[missing], which] = -1.0
            assert self._factor is not None  # made by _rebase
            solved = self._factor.solve(np.ascontiguousarray(rhs[: self.free]))
            self._columns[self._filled : need, : self.free] = solved.T
            self._slot[missing] = np.arange(self._filled, need)
            self._filled = need
        return self._columns[self._slot[runs]]


def _csr_arrays(matrix: sp.csr_matrix) -> tuple[Int32Array, Int32Array, FloatArray]:
    """Return a CSR matrix's (indptr, indices, real values), in its stored order (the compiled loop's sums)."""
    return matrix.indptr, matrix.indices, np.ascontiguousarray(matrix.data.real, dtype=np.float64)


def _sequential(a: FloatArray, b: FloatArray) -> FloatArray:
    """Return ``a @ b`` (matrices), each entry summed over the inner index in order from its first term.

    The order the compiled loops of :mod:`core._switched_kernel` sum in, so the two give the same bits (einsum's
    SIMD loops sum in an order of their own, with fused multiply-adds where the CPU has them). No BLAS: the
    low-rank update's products are small (tens of columns), and BLAS split them over its threads, which on a busy
    machine made a scored state ten times slower (measured: 3.3 ms against 0.3 ms per state).
    """
    out = a[:, 0, None] * b[0]
    for k in range(1, a.shape[1]):
        out = out + a[:, k, None] * b[k]
    return cast(FloatArray, out)


@dataclass(frozen=True, slots=True)
class _Runs:
    """Links grouped into runs (:func:`_chains`): per run and per link."""

    start: IntArray  # (R,) the experience a run starts from
    end: IntArray  # (R,) the experience it ends at
    length: IntArray  # (R,) its links, m
    heading: FloatArray  # (R,) the headings it measures from start to end (windings taken)
    switched: tuple[IntArray, IntArray]  # the runs that are one switched link, and that link (position)
    run: IntArray  # (K,) each link's run
    offset: FloatArray  # (K,) the headings measured along its run from the start to the link's source
    along: FloatArray  # (K,) k/m: how far along its run the link's source lies
    sign: FloatArray  # (K,) +1 where the link points along its run, −1 against


def _chains(n: int, src: IntArray, dst: IntArray, switched: BoolArray, heading: FloatArray) -> _Runs:
    """Return the links grouped into runs between terminals: each switched link alone, fixed links in chains.

    Terminals: experiences with other than two links, or with a switched one, and each part's lowest experience.
    ``heading``: each link's measured heading change (windings taken).
    """
    degree = np.bincount(np.concatenate([src, dst]), minlength=n)
    terminal = degree != 2
    terminal[src[switched]] = terminal[dst[switched]] = True
    if src.size:
        _, part = connected_components(sp.csr_matrix((np.ones(src.size), (src, dst)), shape=(n, n)), directed=False)
        lowest = np.full(int(part.max()) + 1, n, dtype=np.int64)
        np.minimum.at(lowest, part[degree > 0], np.flatnonzero(degree > 0))
        terminal[lowest[lowest < n]] = True
    fixed, alone = np.flatnonzero(~switched), np.flatnonzero(switched)
    chain = _walk(n, np.stack([src[fixed], dst[fixed]], axis=1), terminal, heading[fixed])
    count = chain.length.size
    run = np.empty(src.size, dtype=np.int64)
    run[fixed] = chain.run
    run[alone] = count + np.arange(alone.size)
    offset, along, sign = np.zeros(src.size), np.zeros(src.size), np.ones(src.size)
    offset[fixed], along[fixed], sign[fixed] = chain.offset, chain.along, chain.sign
    return _Runs(
        start=np.concatenate([chain.start, src[alone]]), end=np.concatenate([chain.end, dst[alone]]),
        length=np.concatenate([chain.length, np.ones(alone.size, dtype=np.int64)]),
        heading=np.concatenate([chain.heading, heading[alone]]),
        switched=(count + np.arange(alone.size), alone), run=run, offset=offset, along=along, sign=sign,
    )  # fmt: skip


def _walk(n: int, ends: IntArray, terminal: BoolArray, heading: FloatArray) -> _Runs:
    """Return the chains of the links ``ends`` (f, 2): fixed links whose inner experiences are not ``terminal``.

    A link's end at a terminal gets a node of its own (n + 2·link + end), so that the links form paths, the
    chains; each is walked breadth first from its lowest such node, which gives every node its depth k along its
    chain and the headings measured from the start to it (:func:`sums_to_root`). ``switched`` is left empty.
    """
    f = ends.shape[0]
    node = np.where(terminal[ends], n + 2 * np.arange(f)[:, None] + np.arange(2), ends)
    size = n + 2 * f  # and a root, ``size``, above every chain's start
    graph = sp.csr_matrix((np.ones(f), (node[:, 0], node[:, 1])), shape=(size + 1, size + 1))
    _, component = connected_components(graph, directed=False)
    copies = node[terminal[ends]]
    first = np.full(size + 1, size + 1, dtype=np.int64)
    np.minimum.at(first, component[copies], copies)  # each chain's start: its lowest terminal node
    starts = first[first <= size]
    walk = graph + sp.csr_matrix((np.ones(starts.size), (np.full(starts.size, size), starts)), shape=graph.shape)
    _, pred = breadth_first_order(walk, size, directed=False, return_predecessors=True)
    parent = np.where((pred >= 0) & (pred != size), pred, np.arange(size + 1))
    along_run = parent[node[:, 1]] == node[:, 0]  # the link points away from its chain's start
    step = np.zeros(size + 1)
    step[np.where(along_run, node[:, 1], node[:, 0])] = np.where(along_run, heading, -heading)
    measured, _ = sums_to_root(parent, step)
    depth, _ = sums_to_root(parent, (parent != np.arange(size + 1)).astype(np.int64))
    label = np.unique(component[node[:, 0]], return_inverse=True)[1].astype(np.int64)
    count = int(label.max()) + 1 if f else 0
    length = np.zeros(count, dtype=np.int64)
    np.maximum.at(length, label, depth[node].max(axis=1, initial=0))
    far = node[np.arange(f), np.argmax(depth[node], axis=1)] if f else np.zeros(0, np.int64)
    last = np.zeros(count, dtype=np.int64)
    last[label[depth[far] == length[label]]] = far[depth[far] == length[label]]
    begin = np.zeros(count, dtype=np.int64)
    begin[label] = first[component[node[:, 0]]]
    flat = ends.ravel()  # a terminal node n + 2·link + end is that link end's experience
    return _Runs(
        start=flat[begin - n], end=flat[last - n], length=length, heading=measured[last],
        switched=(np.zeros(0, np.int64), np.zeros(0, np.int64)), run=label, offset=measured[node[:, 0]],
        along=depth[node[:, 0]] / np.maximum(length[label], 1), sign=np.where(along_run, 1.0, -1.0),
    )  # fmt: skip


def _one_anchor_each(n: int, src: IntArray, dst: IntArray, anchor: BoolArray) -> bool:
    """Return whether every connected part of the graph holds exactly one anchor among its linked experiences."""
    if src.size == 0:
        return True
    _, labels = connected_components(sp.csr_matrix((np.ones(src.size), (src, dst)), shape=(n, n)), directed=False)
    linked = np.zeros(n, dtype=bool)
    linked[src] = linked[dst] = True
    parts = np.unique(labels[linked])
    count = np.bincount(labels[linked & np.asarray(anchor, dtype=bool)], minlength=int(labels.max()) + 1)
    return bool(np.all(count[parts] == 1))


def _local_indices(src: IntArray, dst: IntArray) -> tuple[IntArray, IntArray, int]:
    """Return the links' ends as indices among the free experiences of their graph, and their number.

    Each connected part's lowest experience is its gauge, held at the origin: its index is the number of free
    experiences (one past the last), where the solvers keep a zero.
    """
    if src.size == 0:
        return src.astype(np.int64), dst.astype(np.int64), 0
    nodes = np.unique(np.concatenate([src, dst]))
    size = nodes.size
    a, b = np.searchsorted(nodes, src), np.searchsorted(nodes, dst)
    _, labels = connected_components(sp.csr_matrix((np.ones(a.size), (a, b)), shape=(size, size)), directed=False)
    gauge = np.zeros(size, dtype=bool)
    gauge[np.unique(labels, return_index=True)[1]] = True  # the first (lowest) node of each part
    index = np.cumsum(~gauge) - 1
    free = int(np.count_nonzero(~gauge))
    index[gauge] = free
    return index[a], index[b], free

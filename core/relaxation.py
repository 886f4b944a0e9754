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
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
from scipy.linalg import LinAlgError
from scipy.linalg.lapack import dpotrf, dpotrs
from scipy.sparse.linalg import splu

from core._buffers import GrowBuffer

TWO_PI = 2.0 * math.pi


def residuals(pose: np.ndarray, src: np.ndarray, dst: np.ndarray, transform: np.ndarray) -> np.ndarray:
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
    out[:, 3] = np.remainder(out[:, 3] - transform[:, 3] + math.pi, TWO_PI) - math.pi
    return out


def roots(parent: np.ndarray) -> np.ndarray:
    """Return the union-find root of every node (pointer jumping over a parent array)."""
    root = parent.copy()
    while True:
        nxt = root[root]
        if np.array_equal(nxt, root):
            return root
        root = nxt


def sums_to_root(parent: np.ndarray, step: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


def _movable(n: int, src: np.ndarray, dst: np.ndarray, anchor: np.ndarray) -> np.ndarray | None:
    """Return the mask (n,) of experiences a solve may move: linked and not anchored (None: there are none)."""
    if src.size == 0:
        return None
    linked = np.zeros(n, dtype=bool)
    linked[src] = True
    linked[dst] = True
    free = linked & ~anchor
    return free if free.any() else None


def solve(
    pose: np.ndarray, src: np.ndarray, dst: np.ndarray, transform: np.ndarray, anchor: np.ndarray, passes: int = 8
) -> np.ndarray:
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

    def solve_field(measured: np.ndarray, fixed_values: np.ndarray) -> np.ndarray:
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
    out[free_idx, 3] = np.remainder(yaw[free_idx] + math.pi, TWO_PI) - math.pi
    return out


def solve_block(
    pose: np.ndarray,
    ids: np.ndarray,
    owner: np.ndarray,
    src: np.ndarray,
    dst: np.ndarray,
    transform: np.ndarray,
) -> tuple[np.ndarray, bool]:
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


def sorted_unique(ids: np.ndarray) -> np.ndarray:
    """Return the distinct values of an integer array in increasing order (``np.unique`` without its overhead)."""
    ordered = np.sort(ids)
    if ordered.size < 2:
        return ordered
    keep = np.empty(ordered.size, dtype=bool)
    keep[0] = True
    np.not_equal(ordered[1:], ordered[:-1], out=keep[1:])
    return ordered[keep]


def member_of(values: np.ndarray, sorted_set: np.ndarray) -> np.ndarray:
    """Return a mask: is each of ``values`` in ``sorted_set`` (increasing, non-empty)? ``np.isin`` by bisection."""
    slot = np.minimum(np.searchsorted(sorted_set, values), sorted_set.size - 1)
    return sorted_set[slot] == values


def _cholesky(matrix: np.ndarray) -> np.ndarray:
    """Return the lower Cholesky factor of a symmetric positive definite matrix (LAPACK ``dpotrf``).

    The LAPACK routine scipy's ``cho_factor`` wraps, called directly: on the
    relaxation's small blocks the wrapper's checks cost more than the factorisation.
    """
    factor, info = dpotrf(matrix, lower=1, clean=0)
    if info != 0:
        msg = f"relaxation block is not positive definite (dpotrf info {info})"
        raise LinAlgError(msg)
    return factor


def _cho_solve(factor: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve ``L·Lᵀ·x = rhs`` for the lower factor of :func:`_cholesky` (LAPACK ``dpotrs``)."""
    solution, info = dpotrs(factor, rhs, lower=1)
    if info != 0:
        msg = f"dpotrs failed (info {info})"
        raise LinAlgError(msg)
    return solution


class Incidence:
    """The links touching each experience, as a padded (E, W) table; W doubles when a row fills."""

    def __init__(self, capacity: int = 64, width: int = 4) -> None:
        self._table = np.full((max(capacity, 1), width), -1, dtype=np.int64)
        self._degree = np.zeros(max(capacity, 1), dtype=np.int64)
        self._n = 0

    @property
    def degree(self) -> np.ndarray:
        """Return the number of links of every experience (view)."""
        return self._degree[: self._n]

    def add_nodes(self, count: int) -> None:
        """Append ``count`` experiences without links."""
        need = self._n + count
        if need > self._table.shape[0]:
            capacity = max(need, 2 * self._table.shape[0])
            table = np.full((capacity, self._table.shape[1]), -1, dtype=np.int64)
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
                wider = np.full((self._table.shape[0], 2 * self._table.shape[1]), -1, dtype=np.int64)
                wider[:, : self._table.shape[1]] = self._table
                self._table = wider
            self._table[node, slot] = link
            self._degree[node] = slot + 1

    def gather(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return (links, owner): the links of ``ids`` grouped by experience, and each one's position in ``ids``."""
        width = int(self._degree[ids].max()) if ids.size else 0
        rows = self._table[:, :width][ids]
        mask = rows >= 0
        owner = np.nonzero(mask)[0]
        return rows[mask], owner

    @classmethod
    def from_links(cls, n: int, src: np.ndarray, dst: np.ndarray) -> Incidence:
        """Build the table of ``n`` experiences from link endpoints (links listed in id order at each end)."""
        k = src.size
        ends = np.concatenate([src, dst]).astype(np.int64)
        links = np.tile(np.arange(k, dtype=np.int64), 2)
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

    def push(self, ids: np.ndarray) -> None:
        """Append the ids not queued yet (each once, in increasing order)."""
        if ids.size == 0:
            return
        ids = sorted_unique(ids)
        self.reserve(int(ids[-1]) + 1)
        new = ids[~self._queued[ids]]
        if new.size:
            self._queued[new] = True
            self._items.extend(new)

    def extend_ordered(self, ids: np.ndarray) -> None:
        """Append distinct ids in the given order (restoring a saved queue)."""
        ids = np.asarray(ids, dtype=np.int64)
        if ids.size == 0:
            return
        self.reserve(int(ids.max()) + 1)
        new = ids[~self._queued[ids]]
        self._queued[new] = True
        self._items.extend(new)

    def pop(self, count: int) -> np.ndarray:
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

    def items(self) -> np.ndarray:
        """Return the queued ids in order (a copy)."""
        return self._items.view[self._head :].copy()

    def clear(self) -> None:
        """Empty the queue."""
        self._queued[self.items()] = False
        self._items = GrowBuffer((), np.int64)
        self._head = 0


def length_weights(distance: np.ndarray, length: float) -> np.ndarray:
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
    pose: np.ndarray,
    src: np.ndarray,
    dst: np.ndarray,
    transform: np.ndarray,
    anchor: np.ndarray,
    heading_weight: float = 1.0,
    iterations: int = 3,
    weight: np.ndarray | None = None,
) -> np.ndarray:
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
    out[free, 3] = np.remainder(out[free, 3] + math.pi, TWO_PI) - math.pi
    return out

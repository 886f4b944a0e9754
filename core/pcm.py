"""Pairwise consistency of loop links: a start for the robust relaxation that many wrong links cannot fool.

Pairwise Consistency Maximisation (Mangelson, Dominic, Eustice & Vasudevan, "Pairwise Consistent
Measurement Set Maximization for Robust Multi-robot Map Merging", ICRA 2018): two loop links are
consistent when the cycle they close with the odometry between their ends comes back to where it
started, within what the odometry can have drifted along that cycle. For links l₁ = (i → j, T₁) and
l₂ = (a → b, T₂), with X the poses dead-reckoned over the odometry alone (and the merge links that
bridge components), the cycle i → a → b → j → i gives (PCM Eq. 4, in SE(2) × ℝ)

    E = (X_i⁻¹ X_a) · T₂ · (X_b⁻¹ X_j) · T₁⁻¹,

and the pair is consistent when ``z = √((‖E_xyz‖/(drift·L))² + (E_ψ/(yaw_drift·L))²) ≤ c̄``, with
``L = path(i, a) + path(b, j) + 2s`` the odometry travelled between the links' ends along the tree
(``s``, one link length, for each link's own error) — the normalisation of
:func:`core.robust.normalised_residuals` applied to a cycle instead of one link. Each pair is tried with
l₂ both ways round and the shorter cycle is used. Ends joined by no odometry path are consistent (no
cycle, no evidence).

PCM then looks for the largest set of mutually consistent links (a maximum clique of the
consistency graph). Here the clique is found greedily (links in decreasing number of consistent
partners, each kept when it agrees with every link kept so far): it is only a *start* for
:func:`core.robust.switch_off_outliers`, whose TLS cost then decides (with a margin: see there). Why it
helps: wrong links that outnumber the true ones bend the all-links solution until several fit it, and the
greedy descent from there stops in that bend; a true closure is consistent with the true closures near it
along the route, a random wrong one is not. Its known weakness, as PCM's: false closures of one self-aliased
place are consistent with one another.
"""

from __future__ import annotations

from functools import cached_property
from typing import cast

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, dijkstra

from core.angles import wrap_angle
from core.arrays import BoolArray, FloatArray, IntArray
from core.relaxation import sums_to_root
from core.se3 import compose, inverse, relative

#: pairs whose cycle closes within this many drift bounds are consistent. Strict on purpose: the clique is a
#: seed that must hold no wrong link; the TLS swap-in of :func:`core.robust.switch_off_outliers` adds the true
#: links it left out (measured on ``cave3d`` with 20 wrong links of 1-2 m: at 0.5 the clique held 8 of 11 true
#: closures and no wrong link; at 1, up to 8 wrong ones; true pairs close within 1.03 at most)
PAIR_THRESHOLD = 0.5
#: a link whose own cycle with the odometry closes beyond this many allowances is wrong, whatever agrees with it.
#: Measured on the final maps of 25 simulated runs (``symmetric-overlap`` 0-9, ``twin-overlap`` 0-4 and 5-7 with
#: 40 m turns alike, ``cave3d`` 0-1, ``ellipse``, ``bridge``, ``chain5``, ``symmetric`` 1 and 5), links the
#: odometry joins: 27 of 32 false closures (true gap ≥ 3 m) above 1.5 (the others 0.78-1.46); 10 of 139 true
#: ones (a short cycle with a heading offset in ``cave3d``, 2.4, gap 0.5 m; the self-aliased corridor of
#: ``twin-overlap``, 1.8-1.9, gaps 0.3-1.8 m), which the gate switches off. In single-session maps of the
#: mirror world (``symmetric``) the fold's closures are 3.7-4.2 and its relocalised odometry links 2.2-2.6
UNARY_THRESHOLD = 1.5
#: link lengths a true closure's translation may be off whatever its cycle (:func:`single_consistency`)
UNARY_REACH = 3.0
#: radians a cycle through a merge link may turn whatever its length (the merge's own heading error and a view's),
#: and per metre of odometry along it (:func:`heading_consistency`; a link is flagged above BRIDGED_TURN +
#: BRIDGED_TURN_DRIFT·L; :func:`single_consistency` takes a turn within that bound as heading drift).
#: Measured at the robust checks of 58 simulated runs (``symmetric``, ``symmetric-overlap``,
#: ``twin-overlap`` 20 and 40 m, straight and with turns alike, seeds 0-9), links whose ends only merge links
#: join, last check per link: 567 true (ends < 3 m apart) turn 0-1.93 rad (0.58 over 2.2 m, 1.38 over 89 m,
#: 1.93 over 165 m: the odometry's heading bias, up to 0.015 rad/m); none flagged, the closest at 0.70 of its
#: allowance. 134 false ones turn either < 0.6 rad (50: a copied stretch seen the same way round, left to the TLS
#: cost) or 2.5-3.14 rad (84: a mirror place, paths up to 103 m), all 84 flagged
BRIDGED_TURN = 0.8
BRIDGED_TURN_DRIFT = 0.015
#: cycles at least this many metres long, and this many of them agreeing, estimate the odometry's heading bias
#: (:func:`heading_bias`): over shorter paths a view's own heading error (up to ~0.6 rad) swamps it
BIAS_MIN_PATH = 20.0
BIAS_MIN_CYCLES = 2
#: rad/m a cycle's rate may lie from the bias: a forward view's heading error (±0.35 rad, measured on
#: ``symmetric``'s single routes) over ~90 m; a mirror place's rate lies π/L from it (0.023 at 135 m)
BIAS_AGREEMENT = 0.006
#: rad/m the turn left once the bias is taken out may grow by, over BRIDGED_TURN (:func:`single_consistency`).
#: Measured on the single routes of ``symmetric`` seeds 0-9 (default engine): 60 true cycles of 86-172 m leave
#: 0-35° (allowed 71° at 88 m), 20 mirror ones of 130-137 m 164-180° (allowed 84° at 135 m)
BIAS_TURN_DRIFT = 0.005
#: above this many switchable links the K×K consistency matrix is not built (memory 8·K² bytes, ~1.7 s at 1000)
MAX_LINKS = 1000
#: pairs evaluated at once (bounds the temporaries of :func:`pair_consistency`)
PAIR_CHUNK = 65536
#: pairs from which :meth:`TreePaths.distance` finds their common ancestors by the compiled loop (the same integers
#: either way); below, the numpy passes cost less than loading it
COMPILED_PAIRS = 4096


class TreePaths:
    """Path lengths between experiences along a spanning forest (lowest common ancestor by binary lifting)."""

    def __init__(self, n: int, src: IntArray, dst: IntArray, length: FloatArray, roots: BoolArray) -> None:
        graph = sp.csr_matrix((np.abs(length) + 1e-12, (src, dst)), shape=(n, n))
        graph = graph.maximum(graph.T).tocsr()
        parent = np.arange(n)
        component = np.full(n, -1, dtype=np.int64)
        for root in np.flatnonzero(roots).tolist():
            if component[root] >= 0:
                continue
            order, pred = breadth_first_order(graph, root, directed=False, return_predecessors=True)
            component[order] = root
            parent[order[1:]] = pred[order[1:]]
        child = np.flatnonzero(parent != np.arange(n))
        step = np.zeros(n)
        step[child] = np.asarray(graph[parent[child], child]).ravel()
        from_root, _ = sums_to_root(parent, step)
        self._links, self._parent, self._child, self._step = (n, src, dst), parent, child, step
        depth, _ = sums_to_root(parent, (parent != np.arange(n)).astype(np.int64))
        self.component, self.depth, self.from_root = component, depth, from_root
        levels = max(1, int(depth.max(initial=0)).bit_length())
        self.up = np.empty((levels, n), dtype=np.int64)
        self.up[0] = parent
        for k in range(1, levels):
            self.up[k] = self.up[k - 1][self.up[k - 1]]

    def distance(self, a: IntArray, b: IntArray) -> FloatArray:
        """Return the path length between ``a[k]`` and ``b[k]`` (inf where no path joins them).

        Through their lowest common ancestor: from ``COMPILED_PAIRS`` pairs on by the compiled loop
        (:mod:`core._tree_kernel`), below by :meth:`ancestors` (the same integers, so the same lengths).
        """
        if a.size >= COMPILED_PAIRS:
            from core._tree_kernel import lowest_common_ancestors

            lca = lowest_common_ancestors(self.up, self.depth, a, b)
        else:
            lca = self.ancestors(a, b)
        out = self.from_root[a] + self.from_root[b] - 2.0 * self.from_root[lca]
        joined = (self.component[a] == self.component[b]) & (self.component[a] >= 0)
        return np.where(joined, out, np.inf)

    def ancestors(self, a: IntArray, b: IntArray) -> IntArray:
        """Return the lowest common ancestor of each pair (a[k], b[k]) by binary lifting, every pair at once."""
        a, b = a.copy(), b.copy()
        swap = self.depth[a] < self.depth[b]
        a[swap], b[swap] = b[swap], a[swap]
        x, y = a.copy(), b.copy()
        gap = self.depth[x] - self.depth[y]
        for k in range(self.up.shape[0]):
            lift = (gap >> k) & 1 == 1
            x[lift] = self.up[k][x[lift]]
        for k in range(self.up.shape[0] - 1, -1, -1):
            differ = self.up[k][x] != self.up[k][y]
            x[differ] = self.up[k][x[differ]]
            y[differ] = self.up[k][y[differ]]
        return np.where(x == y, x, self.up[0][x])

    @cached_property
    def travelled(self) -> FloatArray:
        """Return (n,) the metres from each tree's root counted along the links' direction (made when first asked)."""
        n, src, dst = self._links
        way = sp.csr_matrix((np.ones(src.size), (src, dst)), shape=(n, n))
        way = (way - way.T).tocsr()  # +1 where a link runs parent → child, −1 against it
        signed = np.zeros(n)
        child, parent = self._child, self._parent
        if child.size:
            signed[child] = self._step[child] * np.sign(np.asarray(way[parent[child], child]).ravel())
        return sums_to_root(parent, signed)[0]

    def along(self, a: IntArray, b: IntArray) -> FloatArray:
        """Return the metres from ``a[k]`` to ``b[k]`` counted along the links' direction (inf: no path).

        A link walked against its direction counts negative: what a heading drift per metre of
        travel accumulates over the path (:func:`heading_bias`).
        """
        joined = (self.component[a] == self.component[b]) & (self.component[a] >= 0)
        return np.where(joined, self.travelled[b] - self.travelled[a], np.inf)


def single_consistency(
    pose: FloatArray,
    links: tuple[IntArray, IntArray, FloatArray],
    paths: TreePaths,
    scale: tuple[float, float, float],
) -> FloatArray:
    """Return ``z`` (K,) of the cycle each link closes with the odometry between its own ends (inf: no path).

    ``links`` is (src, dst, transform) and ``scale`` (link length ``s``, drift, yaw drift), as for
    :func:`pair_consistency`.

    The one-link case of the pair test (module docstring): E = (X_i⁻¹ X_j) · T⁻¹ over
    ``L = path(i, j) + s``, with the translation allowed ``drift·L`` plus ``UNARY_REACH·s``
    (a view matches its template over a few experience spacings, whatever the cycle's length)
    plus, when the cycle's turn |E_ψ| is one the odometry's heading can drift by
    (``≤ BRIDGED_TURN + BRIDGED_TURN_DRIFT·L``), ``|E_ψ|·L/π``: a heading error swings the route by
    up to its largest lever arm, L/π for a closed path of length L (measured: ``twin`` with 40 m
    look-alikes holding turns, session 2 alone, a true lap closure 31 m off after 1.2 rad of heading
    drift over 155 m). ``z = √((‖E_xyz‖/allowed)² + (E_ψ/(yaw_drift·L))²)``. A loop closure that
    contradicts the odometry of the route between its ends by more than that is wrong whatever
    other links agree with it (a place that looks like another, closed again and again, agrees
    with itself); a mirror place's turn (about π) earns no lever arm.

    When the long cycles show the odometry's heading bias b (:func:`heading_bias`), the turn a
    link's cycle has left once ``b·S`` is taken out (S: the path counted along the direction of
    travel, :meth:`TreePaths.along`) must stay within what is left to explain, ``BRIDGED_TURN +
    BIAS_TURN_DRIFT·L``: ``z ≥ UNARY_THRESHOLD·|E_ψ − b·S| / (BRIDGED_TURN + BIAS_TURN_DRIFT·L)``.
    Without it a mirror place closed over a long cycle, whose turn π + b·S the bias has shrunk,
    passed for drift (``symmetric`` seed 9's single route with ``vt_shift_heading``: six mirror
    closures over 130 m turned 118-123°, within the 158° allowance; they held a fold, APE 5.88 m;
    with the bias taken out 175-184° is left, flagged: 0.53 m).
    """
    src, dst, _ = links
    length, drift, yaw_drift = scale
    cycle = _cycles(pose, links)
    travelled = paths.distance(src, dst) + length
    along = paths.along(src, dst)
    with np.errstate(invalid="ignore"):
        turn = np.abs(cycle[:, 3])
        drifted = turn <= turn_allowance(travelled)  # a turn the odometry's heading explains
        allowed = drift * travelled + UNARY_REACH * length + np.where(drifted, turn * travelled / np.pi, 0.0)
        z = np.hypot(np.linalg.norm(cycle[:, :3], axis=1) / allowed, cycle[:, 3] / (yaw_drift * travelled))
        bias = heading_bias(cycle[:, 3], along)
        if bias is not None:  # the turn left once the odometry's own heading bias is taken out, over its allowance
            unexplained = np.abs(wrap_angle(cycle[:, 3] - bias * along))
            z = np.maximum(z, UNARY_THRESHOLD * unexplained / (BRIDGED_TURN + BIAS_TURN_DRIFT * travelled))
    return np.where(np.isfinite(travelled), z, np.inf)


def heading_bias(turn: FloatArray, along: FloatArray) -> float | None:
    """Return the odometry's heading drift per metre of travel (rad/m) that the closures' cycles show (None: unknown).

    A heading bias b (a gyro's or a visual odometry's, per metre driven) turns the dead-reckoned
    heading by ``b·S`` over a path of ``S`` metres counted along the direction of travel
    (:meth:`TreePaths.along`), so a true closure's cycle turns by ``E_ψ ≈ b·S`` and a mirror
    place's by ``π + b·S``. Rates ``E_ψ/S`` are taken from the cycles at least ``BIAS_MIN_PATH``
    metres long whose rate is one a heading can drift by (``≤ BRIDGED_TURN_DRIFT``); the estimate
    is the median of the largest group that lie within ±``BIAS_AGREEMENT`` of a centre (a
    1-D consensus: true closures agree with one another, a mirror place's rate lies π/S away),
    when it holds at least ``BIAS_MIN_CYCLES`` and no separate group is as large (then the
    map cannot tell). Measured on ``symmetric``'s single routes: true closures over 86-172 m
    give −0.0115 to 0.0093 rad/m by seed (the simulated odometry's yaw bias), mostly within ±0.006
    of their seed's (seed 9: −0.0121 to −0.0023 about −0.0092); the mirror fold's over 130-137 m 0.011-0.018.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = turn / along
        usable = np.isfinite(along) & (np.abs(along) >= BIAS_MIN_PATH) & (np.abs(rate) <= BRIDGED_TURN_DRIFT)
    rate = np.sort(rate[usable])
    if rate.size < BIAS_MIN_CYCLES:
        return None
    upto = np.searchsorted(rate, rate + 2.0 * BIAS_AGREEMENT, side="right")  # the group [i, upto[i]) of each rate
    size = upto - np.arange(rate.size)
    first = int(np.argmax(size))
    rivals = (size == size[first]) & (np.arange(rate.size) >= upto[first])  # as large, and apart from it
    if size[first] < BIAS_MIN_CYCLES or rivals.any():
        return None
    return float(np.median(rate[first : upto[first]]))


def heading_consistency(
    pose: FloatArray, links: tuple[IntArray, IntArray, FloatArray], paths: TreePaths
) -> tuple[FloatArray, FloatArray]:
    """Return (E_ψ, L) (K,): the heading each link's cycle with the tree turns, and the tree path it takes.

    E = (X_i⁻¹ X_j) · T⁻¹ as in :func:`single_consistency` (its heading only), L = path(i, j) (inf: no path).
    """
    src, dst, _ = links
    return _cycles(pose, links)[:, 3], paths.distance(src, dst)


def turn_allowance(travelled: FloatArray) -> FloatArray:
    """Return the radians a cycle over L = ``travelled`` metres may turn: BRIDGED_TURN + BRIDGED_TURN_DRIFT·L."""
    return BRIDGED_TURN + BRIDGED_TURN_DRIFT * travelled


def _cycles(pose: FloatArray, links: tuple[IntArray, IntArray, FloatArray]) -> FloatArray:
    """Return E = (X_i⁻¹ X_j) · T⁻¹ (K, 4) of each link (i → j, T): where its cycle with the poses misses."""
    src, dst, transform = links
    return compose(relative(pose[src], pose[dst]), inverse(transform))


def pair_consistency(
    pose: FloatArray,
    src: IntArray,
    dst: IntArray,
    transform: FloatArray,
    paths: TreePaths,
    length: float,
    drift: float,
    yaw_drift: float,
) -> FloatArray:
    """Return ``z`` (K, K) of every pair of links (module docstring); the diagonal is 0."""
    k = src.size
    p, q = np.triu_indices(k, 1)
    out = np.zeros((k, k))
    ends = np.unique(np.concatenate([src, dst]))  # the experiences the cycles leave from: their inverses, once
    inverted = np.zeros_like(pose)
    inverted[ends] = inverse(pose[ends])
    turn = np.zeros((2, pose.shape[0]))
    turn[:, ends] = np.cos(inverted[ends, 3]), np.sin(inverted[ends, 3])
    frames = (inverted, turn, inverse(transform))
    for lo in range(0, p.size, PAIR_CHUNK):  # bounded temporaries: K = 1000 is 0.5 M pairs
        pp, qq = p[lo : lo + PAIR_CHUNK], q[lo : lo + PAIR_CHUNK]
        z = _pair_z(pose, (src, dst, transform), paths, (length, drift, yaw_drift), pp, qq, frames)
        out[pp, qq] = z
        out[qq, pp] = z
    return out


def _pair_z(
    pose: FloatArray,
    links: tuple[IntArray, IntArray, FloatArray],
    paths: TreePaths,
    scale: tuple[float, float, float],
    p: IntArray,
    q: IntArray,
    frames: tuple[FloatArray, FloatArray, FloatArray],
) -> FloatArray:
    """Return the cycle error ``z`` of link pairs (p[k], q[k]), with q's link taken the way round of shorter paths.

    ``links`` is (src, dst, transform) and ``scale`` (link length, drift, yaw drift), as for
    :func:`pair_consistency`. ``frames``: each experience's inverse pose (on the links' ends) and the cosine and sine
    of its yaw (2, n), and each link's inverse transform: ``relative(X_i, X_a) = X_i⁻¹ ⊕ X_a`` takes them, per
    pair the same numbers as computed there.
    """
    src, dst, transform = links
    length, drift, yaw_drift = scale
    inverted, turn, transform_inv = frames
    best = np.zeros(p.size)
    shortest = np.full(p.size, np.inf)
    t1_inv = transform_inv[p]
    i, j = src[p], dst[p]
    inverse_i, turn_i = inverted[i], (turn[0, i], turn[1, i])
    for a, b, t2 in ((src[q], dst[q], transform[q]), (dst[q], src[q], transform_inv[q])):
        start = compose(inverse_i, pose[a], turn_i)  # X_i⁻¹ ⊕ X_a
        back = compose(inverted[b], pose[j], (turn[0, b], turn[1, b]))  # X_b⁻¹ ⊕ X_j
        cycle = compose(compose(compose(start, t2), back), t1_inv)
        travelled = paths.distance(i, a) + paths.distance(b, j) + 2.0 * length
        z = np.hypot(np.linalg.norm(cycle[:, :3], axis=1) / (drift * travelled), cycle[:, 3] / (yaw_drift * travelled))
        shorter = travelled < shortest  # the cycle of the shorter paths is the one the odometry constrains most
        best[shorter], shortest[shorter] = z[shorter], travelled[shorter]
    return best


def greedy_clique(consistent: BoolArray) -> BoolArray:
    """Return a mask of mutually consistent links: by decreasing degree, each kept when it agrees with all kept."""
    degree = consistent.sum(axis=1)
    order = np.lexsort((np.arange(degree.size), -degree))
    kept = np.zeros(degree.size, dtype=bool)
    for link in order.tolist():
        if consistent[link, kept].all():
            kept[link] = True
    return kept


def map_consistency(
    pose: FloatArray,
    links: tuple[IntArray, IntArray, FloatArray],
    graph: tuple[IntArray, IntArray, FloatArray],
    scale: tuple[float, float],
) -> FloatArray:
    """Return ``z_map`` (K,) per link: its miss in the map as it stood over what the path between its ends allows.

    The translation part of :func:`single_consistency` with the map as it stood in place of the dead reckoning:
    ``pose`` is that map's fixed point (the links on in it solved), ``graph`` (src, dst, metres) its links, and for a
    link ``i → j`` holding ``T``, ``z_map = ‖(X_i ⊕ T)_xyz − X_j‖ / (drift·(L + s) + UNARY_REACH·s)``, with ``L`` the
    shortest path from ``i`` to ``j`` over those links and ``s`` one link length (``scale`` = (s, drift)). For the
    links whose ends the odometry does not join, which :func:`single_consistency` cannot test: a map whose merge and
    loop links have been checked holds its sessions together to within the drift of the path between any two of its
    places, where dead reckoning along one merge link carries that link's error times a lever arm. Heading is not
    weighed: across merge links it has its own test (:func:`heading_consistency`). Flagged above
    ``UNARY_THRESHOLD``, so paths too long to flag anything are not searched: 0 where no such path joins the ends.
    """
    src, dst, transform = links
    if src.size == 0:
        return np.zeros(0)
    s, drift = scale
    miss = np.linalg.norm(compose(pose[src], transform)[:, :3] - pose[dst, :3], axis=1)
    reach = (float(miss.max()) / UNARY_THRESHOLD - UNARY_REACH * s) / drift - s
    if reach <= 0.0:
        return np.zeros(src.size)
    g_src, g_dst, metres = graph
    a, b, w = np.r_[g_src, g_dst], np.r_[g_dst, g_src], np.r_[np.abs(metres), np.abs(metres)] + 1e-12
    order = np.lexsort((w, b, a))  # the shortest of parallel links first
    a, b, w = a[order], b[order], w[order]
    first = np.r_[True, (a[1:] != a[:-1]) | (b[1:] != b[:-1])]
    n = pose.shape[0]
    matrix = sp.csr_matrix((w[first], (a[first], b[first])), shape=(n, n))
    starts, row = np.unique(src, return_inverse=True)
    path = dijkstra(matrix, indices=starts, limit=reach)[row, dst]
    return cast(FloatArray, miss / (drift * (path + s) + UNARY_REACH * s))

"""The compiled loops of the robust check's low-rank scoring: the per-link step, the update, a whole state.

The per-link step of :meth:`core.relaxation.SwitchedRelaxation.residuals` (run sums and right-hand side) and the
Woodbury update's products, the same bits as their numpy versions (below); and :class:`CompiledScoring`, a state of
the robust check scored in one call (its own arithmetic, to rounding; its docstring).

For one set of switches the low-rank solve turns each 2-core link's translation by the heading of its source
(``ψ_a + P + (k/m)·e`` along its run), sums them per run, weighs the runs and gathers them at the free terminals
(the position solve's right-hand side). In numpy that is a dozen whole-array passes over the links (gathers,
``cos``, ``sin``, a complex product, two sparse products); here it is one loop, compiled by numba
(``cache=True``: compiled once per machine, then loaded from ``__pycache__``; ``nogil``).

Arithmetic: every value is computed by the same IEEE operations as the numpy expressions it replaces, so the
two agree to the last bit (tests/core/test_relaxation.py checks it on random graphs):

* the run misclosures ``(f[end] − f[start]) − measured`` and the link headings ``(f[start] + offset) + along·e``
  as numpy evaluates them, left to right, no fused multiply-add (numba does not contract ``a·b + c`` without
  ``fastmath``);
* ``cos`` and ``sin`` from the C library, as numpy's float64 ``cos`` and ``sin`` call them;
* the complex products ``(a + ib)(c + id)`` as numpy's SIMD loop computes them where the CPU has fused
  multiply-adds (x86-64 with FMA3, as every CPU numpy dispatches its AVX2 and AVX-512 loops to):
  ``fma(a, c, −b·d) + i·fma(a, d, b·c)`` (:func:`_fma`, LLVM's ``llvm.fma``; exact on any CPU);
* the sparse products as scipy's ``csr_matvec`` sums them: row by row, in the stored order, from 0, each term
  the complex product of the stored (real) value and the vector's entry, unfused.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, cast

import numpy as np

if TYPE_CHECKING:
    from core.relaxation import SwitchedRelaxation

_COMPILE_LOCK = threading.Lock()
"""Held while the kernel is compiled: two jobs of a server may load it at once."""


def run_sums(
    fields: np.ndarray,
    linear: np.ndarray,
    ends: tuple[np.ndarray, np.ndarray],
    links: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    member: tuple[np.ndarray, np.ndarray, np.ndarray],
    weight: np.ndarray,
    incidence: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return each run's misclosure (2, R), its planar sum (R,) complex and the right-hand side (free, 2).

    ``fields`` (2, free + 1): headings and heights at the terminals; ``linear`` (2, R): what each run measures of
    them; ``ends``: each run's local start and end terminals; ``links``: per 2-core link its heading offset along
    its run, ``k/m``, and its translation along the run (real, imaginary); ``member`` and ``incidence``: the CSR
    arrays (indptr, indices, real values) of the run-membership and the free-terminal incidence matrices;
    ``weight`` (R,): each run's weight, 0 where it is off.
    """
    runs = linear.shape[1]
    miss = np.empty((2, runs))
    planar = np.empty(runs, dtype=np.complex128)
    rhs = np.empty((incidence[0].size - 1, 2))
    _kernel()(np.ascontiguousarray(fields), linear, *ends, *links, *member, weight, *incidence, miss,
              planar.view(np.float64).reshape(-1, 2), rhs, np.empty((runs, 2)))  # fmt: skip
    return miss, planar, rhs


@functools.cache
def _kernel() -> Callable[..., Any]:
    with _COMPILE_LOCK:
        return _compile()


def _compile() -> Callable[..., Any]:
    """Wrap :func:`_fma` as an LLVM intrinsic and compile :func:`_run_sums` (module globals, so numba caches it)."""
    from numba import njit, types
    from numba.extending import intrinsic

    def typed(typingctx: Any, a: Any, b: Any, c: Any) -> Any:  # noqa: ARG001 (numba's intrinsic signature)
        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:  # noqa: ARG001
            return builder.fma(*args)

        return types.float64(types.float64, types.float64, types.float64), codegen

    module = globals()
    module["_fma"] = intrinsic(typed)
    module["_run_sums"] = njit(cache=True, nogil=True)(_run_sums)
    return cast("Callable[..., Any]", module["_run_sums"])  # numba's dispatcher: untyped


def _fma(a: float, b: float, c: float) -> float:
    """Return ``a·b + c`` rounded once (replaced by LLVM's ``llvm.fma.f64`` when compiled; here for reading)."""
    raise NotImplementedError  # only the compiled kernel calls it


def _run_sums(
    fields: np.ndarray, linear: np.ndarray, start: np.ndarray, end: np.ndarray, offset: np.ndarray,
    along: np.ndarray, turned_re: np.ndarray, turned_im: np.ndarray, member_ptr: np.ndarray,
    member_link: np.ndarray, member_value: np.ndarray, weight: np.ndarray, inc_ptr: np.ndarray,
    inc_run: np.ndarray, inc_value: np.ndarray, miss: np.ndarray, planar: np.ndarray, rhs: np.ndarray,
    weighted: np.ndarray,
) -> None:  # fmt: skip
    """Fill ``miss``, ``planar`` (R, 2: real, imaginary) and ``rhs`` (free, 2) (:func:`run_sums`).

    ``weighted`` (R, 2) is scratch. No numpy function inside: loading the kernel needs none of numba's numpy
    registries (which import scipy.linalg and cost ≈ 0.3 s the first time in a process).
    """
    for r in range(linear.shape[1]):
        a, b = start[r], end[r]
        e = (fields[0, b] - fields[0, a]) - linear[0, r]
        miss[0, r] = e
        miss[1, r] = (fields[1, b] - fields[1, a]) - linear[1, r]
        base = fields[0, a]
        sum_re = 0.0
        sum_im = 0.0
        for jj in range(member_ptr[r], member_ptr[r + 1]):
            k = member_link[jj]
            angle = (base + offset[k]) + along[k] * e
            c = math.cos(angle)
            s = math.sin(angle)
            x_re = _fma(c, turned_re[k], -(s * turned_im[k]))
            x_im = _fma(c, turned_im[k], s * turned_re[k])
            v = member_value[jj]
            sum_re += v * x_re - 0.0 * x_im
            sum_im += v * x_im + 0.0 * x_re
        planar[r, 0] = sum_re
        planar[r, 1] = sum_im
        w = weight[r]
        weighted[r, 0] = _fma(sum_re, w, -(sum_im * 0.0))
        weighted[r, 1] = _fma(sum_re, 0.0, sum_im * w)
    for i in range(inc_ptr.size - 1):
        sum_re = 0.0
        sum_im = 0.0
        for jj in range(inc_ptr[i], inc_ptr[i + 1]):
            v = inc_value[jj]
            y_re = weighted[inc_run[jj], 0]
            y_im = weighted[inc_run[jj], 1]
            sum_re += v * y_re - 0.0 * y_im
            sum_im += v * y_im + 0.0 * y_re
        rhs[i, 0] = sum_re
        rhs[i, 1] = sum_im


def low_rank_fields(
    fields: np.ndarray, measured: np.ndarray, columns: np.ndarray, ends: tuple[np.ndarray, np.ndarray],
    inverse: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """Return the headings and heights at the terminals over A from R's (2, free + 1): Woodbury's update.

    ``fields + M·W − ((fields + M·W)[ends] · C⁻ᵀ)·W`` with ``M`` = ``measured`` (2, D), each changed run's measure
    signed +1 on in A, ``W`` = ``columns`` (D, free + 1) and ``C⁻¹`` = ``inverse`` (D, D); each product summed over
    D in order from its first term (:func:`core.relaxation._sequential`, the numpy version, gives the same bits).
    """
    out = np.empty_like(fields)
    _kernels()["fields"](fields, measured, columns, ends[0], ends[1], inverse, out, np.empty((2, 2, measured.shape[1])))
    return out


def low_rank_positions(solved: np.ndarray, columns: np.ndarray, ends: tuple[np.ndarray, np.ndarray],
                       inverse: np.ndarray) -> np.ndarray:  # fmt: skip
    """Return the positions at the terminals over A (free + 1,) complex from R's solve ``solved`` (free, 2).

    ``xy − (C⁻¹ · xy[ends])·W``, real and imaginary parts apart, each product summed in order as
    :func:`low_rank_fields`.
    """
    out = np.zeros((columns.shape[1], 2))
    _kernels()["positions"](solved, columns, ends[0], ends[1], inverse, out, np.empty((2, 2, inverse.shape[0])))
    return out.view(np.complex128).ravel()


@functools.cache
def _kernels() -> dict[str, Callable[..., Any]]:
    with _COMPILE_LOCK:
        from numba import njit

        return {"fields": njit(cache=True, nogil=True)(_fields), "positions": njit(cache=True, nogil=True)(_positions)}


def _fields(fields: np.ndarray, measured: np.ndarray, columns: np.ndarray, start: np.ndarray, end: np.ndarray,
            inverse: np.ndarray, out: np.ndarray, scratch: np.ndarray) -> None:  # fmt: skip
    """Fill ``out`` with :func:`low_rank_fields` (``scratch`` (2, 2, D))."""
    d, n = columns.shape
    for i in range(2):
        for j in range(n):
            acc = measured[i, 0] * columns[0, j]
            for k in range(1, d):
                acc = acc + measured[i, k] * columns[k, j]
            out[i, j] = fields[i, j] + acc
        for m in range(d):
            scratch[0, i, m] = out[i, end[m]] - out[i, start[m]]
        for m in range(d):
            acc = scratch[0, i, 0] * inverse[m, 0]
            for k in range(1, d):
                acc = acc + scratch[0, i, k] * inverse[m, k]
            scratch[1, i, m] = acc
        for j in range(n):
            acc = scratch[1, i, 0] * columns[0, j]
            for k in range(1, d):
                acc = acc + scratch[1, i, k] * columns[k, j]
            out[i, j] = out[i, j] - acc


def _positions(solved: np.ndarray, columns: np.ndarray, start: np.ndarray, end: np.ndarray, inverse: np.ndarray,
               out: np.ndarray, scratch: np.ndarray) -> None:  # fmt: skip
    """Fill ``out`` (free + 1, 2; zeros) with :func:`low_rank_positions` (``scratch`` (2, 2, D))."""
    d, n = columns.shape
    for j in range(solved.shape[0]):
        out[j, 0] = solved[j, 0]
        out[j, 1] = solved[j, 1]
    for i in range(2):
        for m in range(d):
            scratch[0, i, m] = out[end[m], i] - out[start[m], i]
        for m in range(d):
            acc = inverse[m, 0] * scratch[0, i, 0]
            for k in range(1, d):
                acc = acc + inverse[m, k] * scratch[0, i, k]
            scratch[1, i, m] = acc
        for j in range(n):
            acc = scratch[1, i, 0] * columns[0, j]
            for k in range(1, d):
                acc = acc + scratch[1, i, k] * columns[k, j]
            out[j, i] = out[j, i] - acc


# ------------------------------------------------------------------------------------- a whole state in one call


@dataclass(frozen=True, slots=True)
class ScoreTerms:
    """What the robust check's score of a state takes besides the relaxation: per run of the 2-core, and per link.

    ``scale`` (2, R): the translation and heading residual one link of each run is expected to carry (``z``'s
    denominators, :func:`core.robust._normalise`); ``fixed`` (2, F): the 2-core's never-switched links and their runs
    (their squares count, times ``odometry_weight``, while on); ``can_runs``: the runs of its switchable links
    (truncated squares); ``held``, ``held_prior``: the links with a switch prior and that prior (outliers' worth,
    charged when off); ``standby``, ``standby_scale``: the standby links and ``s / max(s, L)`` of each (their own
    ``z`` when left out, compared with ``reach``). ``threshold`` (c̄), ``rounding``: the relative gap within which a
    ``z`` at c̄, c̄/2 or ``reach`` is reported as near (the search then solves the state in full).
    """

    scale: np.ndarray
    fixed: np.ndarray
    can_runs: np.ndarray
    held: np.ndarray
    held_prior: np.ndarray
    standby: np.ndarray
    standby_scale: np.ndarray
    threshold: float
    reach: float
    rounding: float
    odometry_weight: float


# rows of CompiledScoring's per-run arrays: its data (run_data), the kernel's scratch (run_work), the normal matrix's
# entries each run adds to (run_entries: (a, a), (b, b), (a, b), (b, a) for a run from a to b; −1 at the gauge)
_HEADING, _HEIGHT, _LENGTH, _WEIGHT, _SCALE_T, _SCALE_Y = range(6)
_MISS_HEADING, _MISS_HEIGHT, _PLANAR_RE, _PLANAR_IM, _RUN_Z, _WEIGHT_ON = range(6)
# rows of the per-terminal scratch (node_work): headings and heights over A, positions over A, the position solve's
# right-hand side, its solution over R, a column's right-hand side and solution, the factor's D and two solve rows
_FIELDS, _XY, _RHS, _SOLVED, _UNIT, _UNIT_SOLVED, _DIAGONAL, _Y, _X, _NODE_ROWS = 0, 2, 4, 6, 8, 9, 10, 11, 12, 13
# rows of the per-terminal integers (node_index): the normal matrix's column pointers (CSC), the ordering P and its
# inverse, the factor's column pointers, elimination tree, column counts so far, and the factorisation's scratch
_AP, _ORDER, _INVERSE, _LP, _PARENT, _COUNT, _FLAG, _PATTERN, _INDEX_ROWS = range(9)
# entries of limits, and of counters
_THRESHOLD, _NEAR, _REACH, _NEAR_REACH, _ODOMETRY_WEIGHT, _CLIMBS, _REBASE_AT, _HELD = range(8)
_FILLED, _FACTORED = range(2)
# the kernel's answers: scored; the columns' buffer is full; the reference's normal matrix is singular
_SCORED, _GROW, _SINGULAR = range(3)


class CompiledScoring:
    """The robust check's score of a set of switches, in one compiled call: ``z`` of every link and the TLS cost.

    The steps of :meth:`core.relaxation.SwitchedRelaxation.run_residuals` followed by the check's normalisation and
    cost (:meth:`core.robust._Problem.state`), over the same runs: the runs changed since the reference, and where
    more than ``REBASE`` changed, a new reference at the state — its normal matrix ``Bᵀ W B`` and right-hand side
    assembled run by run, factorised ``P L_R Pᵀ = L D Lᵀ`` (Davis, "Algorithm 849: a concise sparse Cholesky
    factorization package", ACM TOMS 2005, up-looking, on the elimination tree found once for all the runs; the
    ordering ``P`` is SuperLU's minimum degree on them, found once), and its headings and heights solved; the
    changed runs' columns ``W_D`` (solved once per reference and kept), the capacitance's inverse (Gauss–Jordan,
    partial pivoting), the Woodbury update of the headings and heights, each link's translation turned by its
    source's heading and summed per run, the position solve, the update of the positions, each run's ``z``, the
    cost. Python's share per state is one call of a couple of dozen arrays (numba types each argument on every call:
    no tuples, which it types in Python).

    Arithmetic: the same formulas as the numpy path, summed in plain order (the run sums and the right-hand sides run
    by run, not scipy's CSR order; a Cholesky factor, not SuperLU's LU; libm's ``hypot`` for the translation norm,
    where numpy's SIMD loop scales by the larger part). Measured against the numpy path at every state of the
    ``light``, ``matching`` and ``street`` logs' checks: ``z`` within 1.5e-10, 1.7e-7 and 5e-11 of it (relative,
    at least 1), costs within 8e-13, 5.6e-9 and 2e-12; against the full solve on ``matching``, 1.4e-7 (``z``) and
    1.8e-9 (cost) where the numpy path is 2.5e-7 and 4.7e-9 off. The search decides on low-rank values only outside
    ``ROUNDING`` of every threshold and tie (:mod:`core.robust`): the checks' answers are the same bits by either
    path (the logs' checks replayed; tests/core/test_robust.py on random maps). No fused multiply-add contraction,
    no threads: the same bits run to run.
    """

    #: runs changed since the reference beyond which the reference moves to the state scored (a factorisation here
    #: costs about what scoring a state does). Measured on the ``light`` log's checks (CPU of all nine): 4 to 32
    #: within the noise of one another (0.33-0.40 s), 64 0.54 s (the capacitance's inverse grows as its cube).
    REBASE = 16

    def __init__(self, switched: SwitchedRelaxation, terms: ScoreTerms, links: int) -> None:
        self._switched = switched
        self._links = links
        runs, free = switched.length.size, switched.free
        start, end = switched.local_src.astype(np.int64), switched.local_dst.astype(np.int64)
        self._run_index = np.stack([start, end])
        self._run_data = np.stack([switched.linear[0], switched.linear[1], switched.length, switched.weight,
                                   terms.scale[0], terms.scale[1]]).astype(np.float64)  # fmt: skip
        self._link_data = np.stack([switched.offset, switched.along, switched.turned.real, switched.turned.imag])
        self._core_index = np.stack([switched.links, switched.run]).astype(np.int64)
        self._switch_index = np.stack([switched.links[switched.switched[1]], switched.switched[0]]).astype(np.int64)
        self._cost = (np.ascontiguousarray(terms.fixed, dtype=np.int64), terms.can_runs.astype(np.int64),
                      np.r_[terms.held, terms.standby].astype(np.int64),
                      np.r_[terms.held_prior, terms.standby_scale].astype(np.float64))  # fmt: skip
        self._limits = np.array([terms.threshold, terms.rounding * max(1.0, terms.threshold), terms.reach,
                                 terms.rounding * max(1.0, terms.reach), terms.odometry_weight,
                                 0.0 if switched.flat else 1.0, self.REBASE, terms.held.size])  # fmt: skip
        self._normal = _normal_structure(start, end, free)
        self._fields = np.zeros((2, free + 1))
        self._columns = np.zeros((2 * self.REBASE, free + 1))
        self._slot = np.full(switched.switched[0].size, -1, dtype=np.int64)  # each switched run's row in columns
        self._counters = np.zeros(2, dtype=np.int64)  # columns filled; whether a reference is factorised
        self._flags = np.zeros((2, switched.switched[0].size), dtype=bool)  # the reference's switches, the state's
        self._run_work = np.zeros((6, runs))
        self._node_work = np.zeros((_NODE_ROWS, free + 1))
        self._small_work = np.zeros((2 * self.REBASE + 6, self.REBASE))  # capacitance, inverse, measured, products
        self._d_index = np.zeros((3, self.REBASE), dtype=np.int64)  # the changed switched runs, their terminals

    def score(self, active: np.ndarray) -> tuple[np.ndarray, float, bool] | None:
        """Return ``z`` (K,), the TLS cost and whether a ``z`` lies within rounding of a threshold; None to decline.

        Declined (the caller takes the numpy path): ``active`` splits a part of the graph or turns a fixed link off
        (:meth:`core.relaxation.SwitchedRelaxation.run_residuals` answers None there too), or a reference's normal
        matrix is singular to working precision.
        """
        switched = self._switched
        if not switched.usable or not switched.parts.whole(active):
            return None
        kernel = _scoring_kernel()
        node_index, normal_rows, run_entries, normal_values, factor_rows, factor_values = self._normal
        while True:
            z = np.empty(self._links)
            status, cost, near = kernel(active, z, self._run_index, self._run_data, self._link_data,
                                        self._core_index, self._switch_index, *self._cost, self._limits, node_index,
                                        normal_rows, run_entries, normal_values, factor_rows, factor_values,
                                        self._fields, self._columns, self._slot, self._counters, self._flags,
                                        self._run_work, self._node_work, self._small_work, self._d_index)  # fmt: skip
            if status == _SCORED:
                return z, cost, near
            if status == _SINGULAR:
                self._counters[_FACTORED] = 0
                return None
            grown = np.zeros((2 * self._columns.shape[0], self._columns.shape[1]))  # _GROW: more columns to keep
            grown[: self._columns.shape[0]] = self._columns
            self._columns = grown


def _normal_structure(start: np.ndarray, end: np.ndarray, free: int) -> tuple[np.ndarray, ...]:
    """Return the normal matrix's structure over all the runs and its symbolic factorisation, and room for values.

    (node_index (``_INDEX_ROWS``, free + 1), the matrix's row indices (CSC, both triangles), run_entries (4, R),
    its values, the factor's row indices, its values.) The ordering is SuperLU's minimum degree on ``A + Aᵀ``
    (``MMD_AT_PLUS_A``, as :meth:`core.relaxation.SwitchedRelaxation._rebase` factorises).
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    a, b = np.r_[start, end, start, end], np.r_[start, end, end, start]
    keep = (a < free) & (b < free)
    pattern = sp.csc_matrix((np.ones(int(keep.sum())), (a[keep], b[keep])), shape=(free, free))
    pattern.sum_duplicates()
    pattern.sort_indices()
    node_index = np.zeros((_INDEX_ROWS, free + 1), dtype=np.int64)
    node_index[_AP] = pattern.indptr
    rows = pattern.indices.astype(np.int64)
    key = np.repeat(np.arange(free, dtype=np.int64), np.diff(pattern.indptr)) * free + rows
    run_entries = np.full(4 * start.size, -1, dtype=np.int64)
    run_entries[keep] = np.searchsorted(key, b[keep] * free + a[keep])
    order = splu(pattern.tocsc() + sp.identity(free, format="csc") * free, permc_spec="MMD_AT_PLUS_A",
                 diag_pivot_thresh=0.0, options={"SymmetricMode": True}).perm_c  # fmt: skip
    node_index[_INVERSE, :free] = order
    node_index[_ORDER, :free] = np.argsort(order)
    _scoring_kernel()
    _symbolic(node_index, rows, free)
    factor_size = int(node_index[_LP, free])
    return (node_index, rows, run_entries.reshape(4, -1), np.zeros(rows.size), np.zeros(factor_size, np.int64),
            np.zeros(factor_size))  # fmt: skip


@functools.cache
def _scoring_kernel() -> Callable[..., tuple[int, float, bool]]:
    with _COMPILE_LOCK:
        from numba import njit

        module = globals()
        for name in ("_symbolic", "_factorise", "_ldl_solve", "_weights_on", "_rebase", "_changed_runs",
                     "_fill_columns", "_invert", "_axpy", "_woodbury", "_update_fields", "_turned_sums",
                     "_update_positions", "_run_scores", "_state_cost", "_score_state"):  # fmt: skip
            if not hasattr(module[name], "py_func"):  # not compiled yet (two threads may both get here)
                module[name] = njit(cache=True, nogil=True)(module[name])
        return cast("Callable[..., tuple[int, float, bool]]", module["_score_state"])


def _score_state(
    active: np.ndarray, z: np.ndarray, run_index: np.ndarray, run_data: np.ndarray, link_data: np.ndarray,
    core_index: np.ndarray, switch_index: np.ndarray, fixed_index: np.ndarray, can_runs: np.ndarray,
    cost_index: np.ndarray, cost_values: np.ndarray, limits: np.ndarray, node_index: np.ndarray,
    normal_rows: np.ndarray, run_entries: np.ndarray, normal_values: np.ndarray, factor_rows: np.ndarray,
    factor_values: np.ndarray, fields: np.ndarray, columns: np.ndarray, slot: np.ndarray, counters: np.ndarray,
    flags: np.ndarray, run_work: np.ndarray, node_work: np.ndarray, small_work: np.ndarray, d_index: np.ndarray,
) -> tuple[int, float, bool]:  # fmt: skip
    """Fill ``z`` (K,) and return (``_SCORED``, the cost, near a threshold), or another status and nothing.

    The steps of :class:`CompiledScoring`, on its arrays.
    """
    nd = _changed_runs(active, switch_index, flags, d_index)
    if nd > int(limits[_REBASE_AT]) or counters[_FACTORED] == 0:
        factor = (node_index, normal_rows, run_entries, normal_values, factor_rows, factor_values)
        if not _rebase(factor, run_index, run_data, switch_index, flags, fields, slot, counters, run_work, node_work):
            return _SINGULAR, 0.0, False
        nd = 0
    if not _fill_columns(run_index, switch_index, node_index, factor_rows, factor_values, columns, slot, counters,
                         d_index, nd, node_work):  # fmt: skip
        return _GROW, 0.0, False
    for m in range(nd):  # the capacitance S + B_Dᵀ W_D, and each changed run's measure signed +1 on in A
        s = d_index[0, m]
        r = switch_index[1, s]
        d_index[1, m], d_index[2, m] = run_index[0, r], run_index[1, r]
        sign = 1.0 if flags[1, s] else -1.0
        small_work[2 * nd, m] = run_data[_HEADING, r] * sign
        small_work[2 * nd + 1, m] = run_data[_HEIGHT, r] * sign
    for i in range(nd):
        for j in range(nd):
            row = slot[d_index[0, j]]
            diagonal = (1.0 if flags[1, d_index[0, i]] else -1.0) if i == j else 0.0
            small_work[i, j] = (diagonal + columns[row, d_index[2, i]]) - columns[row, d_index[1, i]]
    if not _invert(small_work, nd):
        return _SINGULAR, 0.0, False
    _update_fields(fields, columns, slot, d_index, nd, small_work, node_work)
    _turned_sums(node_work, run_index, run_data, link_data, core_index, switch_index, flags, run_work)
    for i in range(2):
        _ldl_solve(node_index, factor_rows, factor_values, node_work, _RHS + i, _SOLVED + i)
    _update_positions(columns, slot, d_index, nd, small_work, node_work)
    near = _run_scores(node_work, run_index, run_data, limits, run_work)
    for k in range(z.size):
        z[k] = 0.0
    for k in range(core_index.shape[1]):
        z[core_index[0, k]] = run_work[_RUN_Z, core_index[1, k]]
    total, near_reach = _state_cost(active, z, run_work, fixed_index, can_runs, cost_index, cost_values, limits)
    return _SCORED, total, near or near_reach


def _changed_runs(active: np.ndarray, switch_index: np.ndarray, flags: np.ndarray, d_index: np.ndarray) -> int:
    """Fill the state's switches (``flags[1]``) and the first runs changed since the reference (``d_index[0]``).

    Return how many changed (``d_index`` holds as many as it has room for).
    """
    count = 0
    for s in range(switch_index.shape[1]):
        on = active[switch_index[0, s]]
        flags[1, s] = on
        if on != flags[0, s]:
            if count < d_index.shape[1]:
                d_index[0, count] = s
            count += 1
    return count


def _rebase(factor: tuple[np.ndarray, ...], run_index: np.ndarray, run_data: np.ndarray, switch_index: np.ndarray,
            flags: np.ndarray, fields: np.ndarray, slot: np.ndarray, counters: np.ndarray, run_work: np.ndarray,
            node_work: np.ndarray) -> bool:  # fmt: skip
    """Make the state's switches the reference: factorise its normal matrix, solve its headings and heights.

    ``Bᵀ W B`` and ``Bᵀ W m`` over the runs on (``W``: the runs' weights, 0 where off; ``m``: what each run measures
    of the headings and heights), as :meth:`core.relaxation.SwitchedRelaxation._rebase`. False when singular.
    """
    node_index, normal_rows, run_entries, normal_values, factor_rows, factor_values = factor
    free = fields.shape[1] - 1
    for s in range(switch_index.shape[1]):
        flags[0, s] = flags[1, s]
        slot[s] = -1
    counters[_FILLED] = 0
    counters[_FACTORED] = 0
    _weights_on(run_data, switch_index, flags, run_work)
    for p in range(normal_values.size):
        normal_values[p] = 0.0
    for i in range(2):
        for j in range(free + 1):
            node_work[_RHS + i, j] = 0.0
    for r in range(run_index.shape[1]):
        w = run_work[_WEIGHT_ON, r]
        for e in range(4):
            if run_entries[e, r] >= 0:
                normal_values[run_entries[e, r]] += w if e < 2 else -w
        a, b = run_index[0, r], run_index[1, r]
        for i in range(2):
            value = w * run_data[_HEADING + i, r]
            if b < free:
                node_work[_RHS + i, b] += value
            if a < free:
                node_work[_RHS + i, a] -= value
    if not _factorise(node_index, normal_rows, normal_values, factor_rows, factor_values, node_work, free):
        return False
    for i in range(2):
        _ldl_solve(node_index, factor_rows, factor_values, node_work, _RHS + i, _FIELDS + i)
        for j in range(free):
            fields[i, j] = node_work[_FIELDS + i, j]
        fields[i, free] = 0.0
    counters[_FACTORED] = 1
    return True


def _weights_on(run_data: np.ndarray, switch_index: np.ndarray, flags: np.ndarray, run_work: np.ndarray) -> None:
    """Fill each run's weight in the state (``flags[1]``): its own, 0 where it is a switched link that is off."""
    for r in range(run_data.shape[1]):
        run_work[_WEIGHT_ON, r] = run_data[_WEIGHT, r]
    for s in range(switch_index.shape[1]):
        if not flags[1, s]:
            run_work[_WEIGHT_ON, switch_index[1, s]] = 0.0


def _symbolic(node_index: np.ndarray, normal_rows: np.ndarray, n: int) -> None:
    """Fill the elimination tree of ``P A Pᵀ`` and its factor's column pointers (Davis 2005, ``ldl_symbolic``)."""
    ap, order, inverse = node_index[_AP], node_index[_ORDER], node_index[_INVERSE]
    parent, count, flag, lp = node_index[_PARENT], node_index[_COUNT], node_index[_FLAG], node_index[_LP]
    for k in range(n):
        parent[k] = -1
        flag[k] = k
        count[k] = 0
        column = order[k]
        for p in range(ap[column], ap[column + 1]):
            i = inverse[normal_rows[p]]
            if i < k:
                while flag[i] != k:
                    if parent[i] == -1:
                        parent[i] = k
                    count[i] += 1
                    flag[i] = k
                    i = parent[i]
    lp[0] = 0
    for k in range(n):
        lp[k + 1] = lp[k] + count[k]


def _factorise(node_index: np.ndarray, normal_rows: np.ndarray, normal_values: np.ndarray, factor_rows: np.ndarray,
               factor_values: np.ndarray, node_work: np.ndarray, n: int) -> bool:  # fmt: skip
    """Factorise ``P A Pᵀ = L D Lᵀ`` row by row on the elimination tree (Davis 2005, ``ldl_numeric``).

    ``L``'s columns in ``factor_rows``/``factor_values`` from the column pointers; ``D`` in ``node_work[_DIAGONAL]``.
    False when a pivot is not positive and finite (the matrix is singular).
    """
    ap, order, inverse = node_index[_AP], node_index[_ORDER], node_index[_INVERSE]
    parent, count, flag, lp = node_index[_PARENT], node_index[_COUNT], node_index[_FLAG], node_index[_LP]
    pattern, diagonal, y = node_index[_PATTERN], node_work[_DIAGONAL], node_work[_Y]
    for k in range(n):
        y[k] = 0.0
    for k in range(n):
        top = n
        flag[k] = k
        count[k] = 0
        column = order[k]
        for p in range(ap[column], ap[column + 1]):
            i = inverse[normal_rows[p]]
            if i <= k:
                y[i] += normal_values[p]
                length = 0
                while flag[i] != k:
                    pattern[length] = i
                    length += 1
                    flag[i] = k
                    i = parent[i]
                while length > 0:
                    top -= 1
                    length -= 1
                    pattern[top] = pattern[length]
        diagonal[k] = y[k]
        y[k] = 0.0
        for t in range(top, n):
            i = pattern[t]
            yi = y[i]
            y[i] = 0.0
            end = lp[i] + count[i]
            for p in range(lp[i], end):
                y[factor_rows[p]] -= factor_values[p] * yi
            lki = yi / diagonal[i]
            diagonal[k] -= lki * yi
            factor_rows[end] = k
            factor_values[end] = lki
            count[i] += 1
        if not (diagonal[k] > 0.0 and math.isfinite(diagonal[k])):
            return False
    return True


def _ldl_solve(node_index: np.ndarray, factor_rows: np.ndarray, factor_values: np.ndarray, node_work: np.ndarray,
               rhs: int, out: int) -> None:  # fmt: skip
    """Solve ``A x = b`` for row ``rhs`` of ``node_work`` into row ``out`` (free entries): ``P A Pᵀ = L D Lᵀ``."""
    order, lp = node_index[_ORDER], node_index[_LP]
    b, x, result = node_work[rhs], node_work[_X], node_work[out]
    n = node_index.shape[1] - 1
    for k in range(n):
        x[k] = b[order[k]]
    for j in range(n):
        for p in range(lp[j], lp[j + 1]):
            x[factor_rows[p]] -= factor_values[p] * x[j]
    for j in range(n):
        x[j] = x[j] / node_work[_DIAGONAL, j]
    for j in range(n - 1, -1, -1):
        for p in range(lp[j], lp[j + 1]):
            x[j] -= factor_values[p] * x[factor_rows[p]]
    for k in range(n):
        result[order[k]] = x[k]


def _fill_columns(run_index: np.ndarray, switch_index: np.ndarray, node_index: np.ndarray, factor_rows: np.ndarray,
                  factor_values: np.ndarray, columns: np.ndarray, slot: np.ndarray, counters: np.ndarray,
                  d_index: np.ndarray, nd: int, node_work: np.ndarray) -> bool:  # fmt: skip
    """Solve ``W_D``'s columns not kept yet, ``L_R⁻¹ b_r`` (+1 at the run's end, −1 at its start; the gauge's 0).

    False when the buffer is full (nothing is lost: the caller grows it and calls again).
    """
    free = columns.shape[1] - 1
    for m in range(nd):
        s = d_index[0, m]
        if slot[s] >= 0:
            continue
        if counters[_FILLED] == columns.shape[0]:
            return False
        r = switch_index[1, s]
        for j in range(free):
            node_work[_UNIT, j] = 0.0
        if run_index[1, r] < free:
            node_work[_UNIT, run_index[1, r]] = 1.0
        if run_index[0, r] < free:
            node_work[_UNIT, run_index[0, r]] = -1.0
        _ldl_solve(node_index, factor_rows, factor_values, node_work, _UNIT, _UNIT_SOLVED)
        row = counters[_FILLED]
        for j in range(free):
            columns[row, j] = node_work[_UNIT_SOLVED, j]
        columns[row, free] = 0.0
        slot[s] = row
        counters[_FILLED] = row + 1
    return True


def _invert(work: np.ndarray, n: int) -> bool:
    """Put the inverse of ``work[:n, :n]`` in ``work[n:2n, :n]`` (Gauss–Jordan, partial pivoting; the first is lost).

    False when a pivot is zero or not finite.
    """
    for i in range(n):
        for j in range(n):
            work[n + i, j] = 1.0 if i == j else 0.0
    for col in range(n):
        pivot = col
        for r in range(col + 1, n):
            if abs(work[r, col]) > abs(work[pivot, col]):
                pivot = r
        if not abs(work[pivot, col]) > 0.0 or not math.isfinite(work[pivot, col]):
            return False
        if pivot != col:
            for j in range(n):
                work[col, j], work[pivot, j] = work[pivot, j], work[col, j]
                work[n + col, j], work[n + pivot, j] = work[n + pivot, j], work[n + col, j]
        scale = work[col, col]
        for j in range(n):
            work[col, j] = work[col, j] / scale
            work[n + col, j] = work[n + col, j] / scale
        for r in range(n):
            factor = work[r, col]
            if r != col and factor != 0.0:
                for j in range(n):
                    work[r, j] = work[r, j] - factor * work[col, j]
                    work[n + r, j] = work[n + r, j] - factor * work[n + col, j]
    return True


def _update_fields(fields: np.ndarray, columns: np.ndarray, slot: np.ndarray, d_index: np.ndarray, nd: int,
                   small_work: np.ndarray, node_work: np.ndarray) -> None:  # fmt: skip
    """Put the headings and heights over A in ``node_work[_FIELDS:_FIELDS + 2]``: ``f + M·W − ((f + M·W)[ends]·C⁻ᵀ)·W``.

    :func:`low_rank_fields`' formula (``M``: ``small_work[2·nd:2·nd + 2]``, ``C⁻¹``: ``small_work[nd:2·nd]``).
    """
    n = fields.shape[1]
    for i in range(2):
        out = node_work[_FIELDS + i]
        for j in range(n):
            out[j] = fields[i, j]
        for k in range(nd):
            _axpy(small_work[2 * nd + i, k], columns[slot[d_index[0, k]]], out)
        _woodbury(out, columns, slot, d_index, nd, small_work, 2 * nd + 2 + 2 * i)


def _update_positions(columns: np.ndarray, slot: np.ndarray, d_index: np.ndarray, nd: int, small_work: np.ndarray,
                      node_work: np.ndarray) -> None:  # fmt: skip
    """Put the positions over A in ``node_work[_XY:_XY + 2]`` from R's solve: ``xy − (C⁻¹·xy[ends])·W``.

    :func:`low_rank_positions`' formula; the gauge's entry is 0 before the update.
    """
    n = columns.shape[1]
    for i in range(2):
        out, solved = node_work[_XY + i], node_work[_SOLVED + i]
        for j in range(n - 1):
            out[j] = solved[j]
        out[n - 1] = 0.0
        _woodbury(out, columns, slot, d_index, nd, small_work, 2 * nd + 2 + 2 * i)


def _woodbury(out: np.ndarray, columns: np.ndarray, slot: np.ndarray, d_index: np.ndarray, nd: int,
              small_work: np.ndarray, row: int) -> None:  # fmt: skip
    """Subtract ``(C⁻¹·(out[ends] − out[starts]))·W_D`` from ``out`` (rows ``row``, ``row + 1`` of ``small_work``)."""
    for m in range(nd):
        small_work[row, m] = out[d_index[2, m]] - out[d_index[1, m]]
    for m in range(nd):
        acc = 0.0
        for k in range(nd):
            acc = acc + small_work[nd + m, k] * small_work[row, k]
        small_work[row + 1, m] = acc
    for k in range(nd):
        _axpy(-small_work[row + 1, k], columns[slot[d_index[0, k]]], out)


def _axpy(a: float, x: np.ndarray, y: np.ndarray) -> None:
    """``y += a·x``."""
    for j in range(y.size):
        y[j] = y[j] + a * x[j]


def _turned_sums(node_work: np.ndarray, run_index: np.ndarray, run_data: np.ndarray, link_data: np.ndarray,
                 core_index: np.ndarray, switch_index: np.ndarray, flags: np.ndarray,
                 run_work: np.ndarray) -> None:  # fmt: skip
    """Fill each run's misclosure, its planar sum and weight, and the position solve's right-hand side.

    :meth:`core.relaxation.SwitchedRelaxation.run_sums`: each 2-core link's translation turned by its source's
    heading on its run, ``ψ_a + P + (k/m)·e``, summed per run; the right-hand side ``Bᵀ_A W planar`` (free, 2),
    its entries summed run by run.
    """
    headings = node_work[_FIELDS]
    heights = node_work[_FIELDS + 1]
    runs = run_index.shape[1]
    for r in range(runs):
        a, b = run_index[0, r], run_index[1, r]
        run_work[_MISS_HEADING, r] = (headings[b] - headings[a]) - run_data[_HEADING, r]
        run_work[_MISS_HEIGHT, r] = (heights[b] - heights[a]) - run_data[_HEIGHT, r]
        run_work[_PLANAR_RE, r] = 0.0
        run_work[_PLANAR_IM, r] = 0.0
    _weights_on(run_data, switch_index, flags, run_work)
    for k in range(core_index.shape[1]):
        r = core_index[1, k]
        angle = (headings[run_index[0, r]] + link_data[0, k]) + link_data[1, k] * run_work[_MISS_HEADING, r]
        c, s = math.cos(angle), math.sin(angle)
        run_work[_PLANAR_RE, r] += c * link_data[2, k] - s * link_data[3, k]
        run_work[_PLANAR_IM, r] += c * link_data[3, k] + s * link_data[2, k]
    free = node_work.shape[1] - 1
    for i in range(2):
        for j in range(free):
            node_work[_RHS + i, j] = 0.0
    for r in range(runs):
        a, b, w = run_index[0, r], run_index[1, r], run_work[_WEIGHT_ON, r]
        for i in range(2):
            value = w * run_work[_PLANAR_RE + i, r]
            if b < free:
                node_work[_RHS + i, b] += value
            if a < free:
                node_work[_RHS + i, a] -= value


def _run_scores(node_work: np.ndarray, run_index: np.ndarray, run_data: np.ndarray, limits: np.ndarray,
                run_work: np.ndarray) -> bool:  # fmt: skip
    """Fill each run's per-link ``z``; return whether one lies within rounding of c̄ or c̄/2.

    Per link of a run: the translation residual ``|xy[end] − xy[start] − planar|`` (with the height's misclosure
    where the map climbs) and the heading misclosure, each over the run's m links, the heading wrapped to [−π, π)
    (:meth:`core.relaxation.SwitchedRelaxation.run_residuals`), then ``hypot(d / scale_t, ψ / scale_y)``.
    """
    x, y = node_work[_XY], node_work[_XY + 1]
    c, tolerance, climbs = limits[_THRESHOLD], limits[_NEAR], limits[_CLIMBS] != 0.0
    near = False
    for r in range(run_index.shape[1]):
        a, b, length = run_index[0, r], run_index[1, r], run_data[_LENGTH, r]
        distance = math.hypot((x[b] - x[a]) - run_work[_PLANAR_RE, r], (y[b] - y[a]) - run_work[_PLANAR_IM, r])
        if climbs:
            distance = math.hypot(distance, run_work[_MISS_HEIGHT, r])
        turn = run_work[_MISS_HEADING, r] / length
        if abs(turn) > math.pi:
            turn = (turn + math.pi) % (2.0 * math.pi) - math.pi
        value = math.hypot(distance / length / run_data[_SCALE_T, r], turn / run_data[_SCALE_Y, r])
        run_work[_RUN_Z, r] = value
        if abs(abs(value - 0.75 * c) - 0.25 * c) <= tolerance:
            near = True
    return near


def _state_cost(active: np.ndarray, z: np.ndarray, run_work: np.ndarray, fixed_index: np.ndarray,
                can_runs: np.ndarray, cost_index: np.ndarray, cost_values: np.ndarray,
                limits: np.ndarray) -> tuple[float, bool]:  # fmt: skip
    """Return the TLS cost (:meth:`core.robust._Problem.cost`) and whether a standby link's own ``z`` is near reach.

    ``γ·Σ z²`` over the 2-core's never-switched links that are on, ``Σ min(z², c̄²)`` over its switchable ones,
    ``c̄²·prior`` for each held link off, ``2·c̄²`` for each standby link left out beyond its reach.
    """
    run_z = run_work[_RUN_Z]
    c2 = limits[_THRESHOLD] * limits[_THRESHOLD]
    fixed = 0.0
    for k in range(fixed_index.shape[1]):
        if active[fixed_index[0, k]]:
            fixed = fixed + run_z[fixed_index[1, k]] * run_z[fixed_index[1, k]]
    truncated = 0.0
    for k in range(can_runs.size):
        square = run_z[can_runs[k]] * run_z[can_runs[k]]
        truncated = truncated + (c2 if square > c2 else square)
    held = int(limits[_HELD])
    held_off = 0.0
    for k in range(held):
        if not active[cost_index[k]]:
            held_off = held_off + cost_values[k]
    reach, tolerance = limits[_REACH], limits[_NEAR_REACH]
    over, near = 0, False
    for k in range(held, cost_index.size):
        if not active[cost_index[k]]:
            own = z[cost_index[k]] * cost_values[k]
            if own > reach:
                over += 1
            near = near or abs(own - reach) <= tolerance
    total = limits[_ODOMETRY_WEIGHT] * fixed + truncated + c2 * held_off
    return total + 2.0 * c2 * over, near

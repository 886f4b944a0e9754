"""The compiled per-link step of :meth:`core.relaxation.SwitchedRelaxation.residuals`: run sums and right-hand side.

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
from typing import Any, cast

import numpy as np

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

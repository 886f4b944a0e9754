"""The compiled lowest-common-ancestor search of :meth:`core.pcm.TreePaths.distance` (binary lifting, pair by pair).

The numpy version lifts every pair at once, one level of the ancestor table at a time (2·log₂ depth passes of
fancy indexing over all the pairs); here each pair is lifted on its own in one compiled loop (numba,
``cache=True``: compiled once per machine, then loaded from ``__pycache__``; ``nogil``). Integers only: the
ancestors are exactly those of the numpy version (tests/core/test_pcm.py compares them on random forests).
"""

from __future__ import annotations

import functools
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

_COMPILE_LOCK = threading.Lock()
"""Held while the kernel is compiled: two jobs of a server may load it at once."""


def lowest_common_ancestors(up: np.ndarray, depth: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return the lowest common ancestor of each pair (a[k], b[k]) (int64; meaningless where no tree joins them).

    ``up`` (levels, n): the 2^k-th ancestor of each node (a root its own); ``depth`` (n,): links from the root.
    """
    out = np.empty(a.size, dtype=np.int64)
    _kernel()(up, depth, np.ascontiguousarray(a, dtype=np.int64), np.ascontiguousarray(b, dtype=np.int64), out)
    return out


@functools.cache
def _kernel() -> Callable[..., Any]:
    with _COMPILE_LOCK:
        from numba import njit

        return njit(cache=True, nogil=True)(_ancestors)


def _ancestors(up: np.ndarray, depth: np.ndarray, a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """Fill ``out`` with each pair's lowest common ancestor: lift the deeper end to the other's depth, then both."""
    levels = up.shape[0]
    for k in range(a.size):
        x, y = a[k], b[k]
        if depth[x] < depth[y]:
            x, y = y, x
        gap = depth[x] - depth[y]
        level = 0
        while gap > 0:
            if gap & 1:
                x = up[level, x]
            gap >>= 1
            level += 1
        if x != y:
            for level in range(levels - 1, -1, -1):
                if up[level, x] != up[level, y]:
                    x = up[level, x]
                    y = up[level, y]
            x = up[0, x]
        out[k] = x

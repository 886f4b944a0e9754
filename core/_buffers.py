"""Geometrically growing numpy buffers: amortised O(1) appends for per-frame growth."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt


class GrowBuffer:
    """A row buffer of fixed trailing shape whose capacity doubles when full.

    ``view`` is the filled part (no copy). Appending never copies the whole store
    except when the capacity doubles, so N appends cost O(N) in total.
    """

    def __init__(self, row_shape: tuple[int, ...], dtype: npt.DTypeLike, capacity: int = 64) -> None:
        self._data = np.zeros((max(capacity, 1), *row_shape), dtype=dtype)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    @property
    def view(self) -> np.ndarray:
        """Return the filled rows (a view, not a copy)."""
        return self._data[: self._n]

    def _reserve(self, n: int) -> None:
        if n <= self._data.shape[0]:
            return
        capacity = self._data.shape[0]
        while capacity < n:
            capacity *= 2
        grown = np.zeros((capacity, *self._data.shape[1:]), dtype=self._data.dtype)
        grown[: self._n] = self._data[: self._n]
        self._data = grown

    def reserve(self, n: int) -> None:
        """Make room for ``n`` rows in all (the capacity doubles until it holds them), so that appends do not copy."""
        self._reserve(n)

    def append(self, row: npt.ArrayLike) -> int:
        """Append one row and return its index."""
        self._reserve(self._n + 1)
        self._data[self._n] = row
        self._n += 1
        return self._n - 1

    def extend(self, rows: npt.ArrayLike) -> None:
        """Append several rows (first axis) at once."""
        rows = np.asarray(rows, dtype=self._data.dtype)
        k = rows.shape[0]
        self._reserve(self._n + k)
        self._data[self._n : self._n + k] = rows
        self._n += k

    def copy(self) -> np.ndarray:
        """Return a copy of the filled rows."""
        return self._data[: self._n].copy()

    @classmethod
    def from_array(cls, rows: npt.ArrayLike, dtype: npt.DTypeLike) -> GrowBuffer:
        """Build a buffer holding ``rows`` (copied)."""
        rows = np.asarray(rows, dtype=dtype)
        buffer = cls(tuple(rows.shape[1:]), dtype, capacity=max(64, 2 * rows.shape[0]))
        buffer.extend(rows)
        return buffer

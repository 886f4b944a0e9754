"""Geometrically growing numpy buffers: amortised O(1) appends for per-frame growth."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from core.arrays import Float32Array


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


class SharedRows:
    """Rows of fixed trailing shape: read-only blocks shared with the arrays they came from, then appended rows.

    :meth:`share` adds an array as the next rows without copying it (a restored engine's templates stay the
    snapshot's array, a merged engine's the stored map's); :meth:`extend` appends rows to a :class:`GrowBuffer`
    after every block, so appending never copies a shared block. Rows are never written once held.
    """

    def __init__(self, row_shape: tuple[int, ...], dtype: npt.DTypeLike) -> None:
        self._dtype = np.dtype(dtype)
        self._row_shape = tuple(row_shape)
        self._blocks: list[np.ndarray] = []
        self._tail = GrowBuffer(row_shape, self._dtype)

    def __len__(self) -> int:
        return sum(len(block) for block in self._blocks) + len(self._tail)

    @property
    def blocks(self) -> tuple[Float32Array, ...]:
        """Return the shared blocks (read-only arrays, in row order; the appended rows follow them)."""
        return tuple(self._blocks)

    @property
    def view(self) -> Float32Array:
        """Return every row as one read-only array: no copy when the rows are one block, else a new array."""
        parts = [*self._blocks, self._tail.view] if len(self._tail) else list(self._blocks)
        if not parts:
            rows = self._tail.view
        elif len(parts) == 1:
            rows = parts[0]
        else:
            rows = np.concatenate(parts)
        out = rows.view()
        out.flags.writeable = False
        return out

    def share(self, rows: npt.ArrayLike) -> None:
        """Add ``rows`` as the next rows, read-only, without a copy when they have the store's dtype.

        Raises:
            ValueError: rows were appended already (shared blocks come first), or ``rows`` do not have the
                store's row shape.
        """
        if len(self._tail):
            msg = f"rows can be shared only before rows are appended, this store has {len(self._tail)} appended"
            raise ValueError(msg)
        block = np.asarray(rows, dtype=self._dtype).view()
        if block.shape[1:] != self._row_shape:
            msg = f"rows of shape {block.shape[1:]!r} do not fit a store of rows {self._row_shape!r}"
            raise ValueError(msg)
        block.flags.writeable = False
        if len(block):
            self._blocks.append(block)

    def extend(self, rows: npt.ArrayLike) -> None:
        """Append several rows (first axis) at once, after every row held."""
        self._tail.extend(rows)

    def copy(self) -> np.ndarray:
        """Return a copy of every row (one new writable array)."""
        parts = [*self._blocks, self._tail.view]
        return np.concatenate(parts) if len(parts) > 1 else parts[0].copy()

"""Names for the numpy array types the engine passes around: an array's element type is part of its type.

``FloatArray`` is any shape of ``float64`` (poses, activities, costs), ``IntArray`` of ``int64`` (indices, ids,
counts) and ``BoolArray`` of ``bool`` (masks); the narrower element types name themselves.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
Float32Array = npt.NDArray[np.float32]
ComplexArray = npt.NDArray[np.complex128]
IntArray = npt.NDArray[np.int64]
Int32Array = npt.NDArray[np.int32]
Int8Array = npt.NDArray[np.int8]
UInt8Array = npt.NDArray[np.uint8]
UInt64Array = npt.NDArray[np.uint64]
BoolArray = npt.NDArray[np.bool_]

ScalarT = TypeVar("ScalarT", bound=np.generic)
"""An array's element type where a function keeps it (a read-only copy, a sum along a forest)."""
SumT = TypeVar("SumT", np.int64, np.float64)
"""The element type of values a function sums and returns (counts or lengths)."""
IndexT = TypeVar("IndexT", np.int32, np.int64)
"""The element type of an index array where a function keeps it (scipy's graph routines label in int32)."""

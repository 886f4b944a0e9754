"""Wrapping-lattice helpers shared by the pose cells and the experience decisions."""

from __future__ import annotations

from typing import cast

import numpy as np
import numpy.typing as npt

from core.arrays import FloatArray


def wrapped_delta(a: npt.ArrayLike, b: npt.ArrayLike, dims: npt.ArrayLike) -> FloatArray:
    """Return per-axis minimum distances |a-b| on a periodic lattice of size ``dims``.

    Multisession RatSLAM Eq. 2: distances respect the network's periodic boundaries.
    """
    d = np.abs(np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64))
    dims_f = np.asarray(dims, dtype=np.float64)
    d = np.mod(d, dims_f)
    return np.minimum(d, dims_f - d)


def wrapped_distance(a: npt.ArrayLike, b: npt.ArrayLike, dims: npt.ArrayLike) -> FloatArray:
    """Return the wrapped Euclidean lattice distance (OpenRatSLAM ``get_delta_pc``), last axis summed."""
    d = wrapped_delta(a, b, dims)
    return cast(FloatArray, np.sqrt(np.sum(d * d, axis=-1)))


def gaussian_kernel_1d(size: int, var: float) -> FloatArray:
    """Return a normalised 1-D Gaussian of odd ``size`` and width ``var``.

    OpenRatSLAM builds its excitatory/inhibitory weights as
    ``exp(-(Σ (i-c)²) / (2 var²))`` over a ``size``-cube and normalises the sum to 1
    (``norm2d``). That cube is the outer product of these 1-D kernels.
    """
    centre = size // 2
    offsets = np.arange(size, dtype=np.float64) - centre
    k = np.exp(-(offsets * offsets) / (2.0 * var * var))
    return cast(FloatArray, k / k.sum())


def circulant_kernel(dim: int, size: int, var: float) -> FloatArray:
    """Return the (dim, dim) matrix of a circular convolution with the 1-D Gaussian of ``size`` cells.

    ``C[i, j] = k[(i − j) mod dim]``: the kernel's centre sits on the diagonal and
    offsets wrap modulo ``dim`` (a kernel wider than the lattice folds onto itself),
    so ``C @ a`` along one axis is the wrapped spread of Multisession RatSLAM Eq. 3.
    OpenRatSLAM's ``size``-cube of weights is the outer product of these kernels, so
    applying ``C`` along every axis in turn equals its cell-by-cell spread.
    """
    k1 = gaussian_kernel_1d(size, var)
    wrapped = np.zeros(dim, dtype=np.float64)
    np.add.at(wrapped, (np.arange(size) - size // 2) % dim, k1)
    index = np.arange(dim)
    return cast(FloatArray, wrapped[(index[:, None] - index[None, :]) % dim])

"""Transforms of pose-cell lattice coordinates between two sessions' lattices (operations ii–iii).

Axes are (x, y, th) or (x, y, z, th) in cells, every axis wrapping (the network's
periodic faces, Menezes et al. Eq. 2). Heading cell k is the angle ``k·2π/n_th``
and path integration moves layer k along ``(cos, sin)`` of that angle in (x, y).

Two sessions that saw the same place hold two packets for it: ``source`` in the
partial lattice and ``target`` in the loaded one. The lattice offset is
``target − source`` per axis (loaded − partial; the printed Eq. 10 adds the
coordinates, a sign error). Menezes et al. Eq. 11 shifts every partial coordinate
by that offset modulo each dimension. That is right only when the two sessions'
lattice headings agree: if heading cells differ by Δθ, a displacement that the
partial lattice holds at heading θ is held by the loaded one at θ + Δθ, i.e.
rotated by the angle ``Δθ·2π/n_th`` in (x, y). So the coordinate's wrapped
displacement from ``source`` is rotated by that angle about the matched cell, then
added to ``target`` and wrapped; z and θ are only shifted. With Δθ = 0 this is
exactly Eq. 11.

Rotation on a torus is exact for displacements shorter than half the lattice
(the wrapped displacement is unique there); farther coordinates are mapped from
their shortest wrapped displacement, which is the best the periodic lattice can
say about them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import numpy as np
import numpy.typing as npt

from core.arrays import FloatArray


def wrap_coords(coords: npt.ArrayLike, dims: npt.ArrayLike) -> FloatArray:
    """Return coordinates wrapped into [0, dim) per axis (Menezes et al. Eq. 11's ``mod``)."""
    d = np.asarray(dims, dtype=np.float64)
    out = np.mod(np.asarray(coords, dtype=np.float64), d)
    return np.where(out >= d, 0.0, out)  # fmod rounding can return dim itself


def signed_delta(a: npt.ArrayLike, b: npt.ArrayLike, dims: npt.ArrayLike) -> FloatArray:
    """Return the shortest wrapped displacement ``a − b`` per axis, in [−dim/2, dim/2)."""
    d = np.asarray(dims, dtype=np.float64)
    delta = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    return delta - d * np.floor(delta / d + 0.5)


@dataclass(frozen=True)
class LatticeTransform:
    """Maps partial-lattice coordinates onto the loaded lattice: rotate about the matched cell, shift, wrap.

    Attributes:
        dims: lattice shape (D,), axes (x, y, [z,] th).
        source: the matched packet in the partial lattice (D,), cells.
        target: the same place's packet in the loaded lattice (D,), cells.
    """

    dims: tuple[float, ...]
    source: tuple[float, ...]
    target: tuple[float, ...]

    def __post_init__(self) -> None:
        n = len(self.dims)
        if n not in (3, 4) or len(self.source) != n or len(self.target) != n:
            msg = f"lattice rank must be 3 or 4 with matching anchors, got dims {self.dims!r}, " \
                  f"source {self.source!r}, target {self.target!r}"
            raise ValueError(msg)

    @classmethod
    def between(cls, dims: npt.ArrayLike, source: npt.ArrayLike, target: npt.ArrayLike) -> LatticeTransform:
        """Build the transform taking packet ``source`` (partial lattice) onto ``target`` (loaded lattice)."""
        d = np.asarray(dims, dtype=np.float64)
        return cls(
            tuple(d.tolist()),
            tuple(wrap_coords(source, d).tolist()),
            tuple(wrap_coords(target, d).tolist()),
        )

    @property
    def offset(self) -> FloatArray:
        """Return the lattice offset ``target − source`` (D,) wrapped to [−dim/2, dim/2) (corrected Eq. 10)."""
        return signed_delta(self.target, self.source, self.dims)

    @property
    def heading_cells(self) -> float:
        """Return the heading offset Δθ in heading cells (the offset's last axis)."""
        return float(self.offset[-1])

    @property
    def heading_rad(self) -> float:
        """Return the heading offset as an angle: ``Δθ·2π/n_th``."""
        return self.heading_cells * 2.0 * math.pi / self.dims[-1]

    def apply(self, coords: npt.ArrayLike) -> FloatArray:
        """Return ``f(coords)`` (..., D): Eq. 11 with the (x, y) displacement rotated by the heading offset.

        ``f(c) = wrap(target + R(Δθ)·δ(c − source))`` where δ is the shortest wrapped
        displacement and R rotates (x, y) only; z and θ keep their displacement.
        """
        c = np.asarray(coords, dtype=np.float64)
        dims = np.asarray(self.dims)
        delta = signed_delta(c, np.asarray(self.source), dims)
        angle = self.heading_rad
        if angle != 0.0:
            cos_a, sin_a = math.cos(angle), math.sin(angle)
            # exact on multiples of 90°, so integer cells stay integer
            cos_a = 0.0 if abs(cos_a) < 1e-12 else cos_a
            sin_a = 0.0 if abs(sin_a) < 1e-12 else sin_a
            dx, dy = delta[..., 0].copy(), delta[..., 1].copy()
            delta[..., 0] = cos_a * dx - sin_a * dy
            delta[..., 1] = sin_a * dx + cos_a * dy
        return wrap_coords(np.asarray(self.target) + delta, dims)

    def inverse(self) -> LatticeTransform:
        """Return the transform taking loaded coordinates back to the partial lattice."""
        return LatticeTransform(self.dims, self.target, self.source)

    def then(self, after: LatticeTransform) -> LatticeTransform:
        """Return ``after ∘ self`` (apply ``self`` first), exact for displacements within half the lattice."""
        if tuple(after.dims) != tuple(self.dims):
            msg = f"cannot compose transforms of lattices {self.dims!r} and {after.dims!r}"
            raise ValueError(msg)
        return LatticeTransform(self.dims, self.source, tuple(after.apply(self.target).tolist()))


def splat(dims: tuple[int, ...], centre: npt.ArrayLike) -> FloatArray:
    """Return a unit activity whose mass sits at fractional ``centre`` (multilinear weights over 2^D cells).

    Operation (ii): the merged network's packet starts at one point; spreading the unit
    over the neighbouring cells keeps the sub-cell position for the population-vector decode.
    """
    point = wrap_coords(centre, dims)
    base = np.floor(point).astype(np.int64)
    frac = point - base
    activity = np.zeros(dims, dtype=np.float64)
    rank = len(dims)
    for corner in range(1 << rank):
        bits = [(corner >> a) & 1 for a in range(rank)]
        weight = float(np.prod([frac[a] if bits[a] else 1.0 - frac[a] for a in range(rank)]))
        if weight > 0.0:
            cell = tuple(int((base[a] + bits[a]) % dims[a]) for a in range(rank))
            activity[cell] += weight
    total = activity.sum()
    return cast(FloatArray, activity / total)

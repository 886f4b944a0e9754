"""Locality-sensitive binary hashing (sLSBH): a fixed Gaussian projection, then top-k/bottom-k bits.

PoseidonSLAM Eq. 4.2 (thesis §4.2.2, NeoSLAM Eqs 3.35–3.37): with p = L/2 and the embedding y,
``v = Pᵀ y ∈ R^p`` (P ∈ R^{d×p}, N(0, 1) entries, each column scaled to unit norm), ``k = ⌊s·p⌋``;
bit i < p is set when i is among the k largest v, bit p + i when i is among the k smallest v. The code
has exactly 2k ones (the thesis's "2k active bits"; notes §11.2). Modalities are fused by bitwise OR
(Eq. 4.3). Ties in v go to the lower index (stable sort), so the code is a function of v alone.
"""

from __future__ import annotations

import functools
import hashlib

import numpy as np
import torch

from core.arrays import UInt8Array


def projection(dims: int, half: int, seed: int) -> torch.Tensor:
    """Return the (dims, half) float32 LSBH matrix: N(0, 1) from a CPU generator seeded ``seed``, unit columns.

    Drawn once per argument set and handed out as copies (a session builds several cortices from one seed).
    """
    return _drawn_projection(int(dims), int(half), int(seed))[0].clone()


def projection_digest(dims: int, half: int, seed: int) -> UInt8Array:
    """Return :func:`digest` of :func:`projection` ``(dims, half, seed)`` (computed once per argument set)."""
    return _drawn_projection(int(dims), int(half), int(seed))[1].copy()


@functools.lru_cache(maxsize=2)
def _drawn_projection(dims: int, half: int, seed: int) -> tuple[torch.Tensor, UInt8Array]:
    """Return the projection of one argument set and its digest (cached: never modify them)."""
    generator = torch.Generator(device="cpu").manual_seed(seed)
    matrix = torch.randn(dims, half, generator=generator, dtype=torch.float32)
    matrix /= torch.linalg.vector_norm(matrix, dim=0, keepdim=True).clamp_min(1e-12)
    return matrix, digest(matrix)


def digest(matrix: torch.Tensor | np.ndarray) -> UInt8Array:
    """Return the SHA-256 of the matrix's float32 bytes as a (32,) uint8 array (checks a regenerated projection)."""
    data = matrix.detach().cpu().numpy() if isinstance(matrix, torch.Tensor) else np.asarray(matrix)
    return np.frombuffer(hashlib.sha256(np.ascontiguousarray(data, dtype=np.float32).tobytes()).digest(), np.uint8)


def lsbh_bits(v: torch.Tensor, k: int) -> torch.Tensor:
    """Return the (…, 2p) bool SDR of projections ``v`` (…, p): top-k in the first half, bottom-k in the second.

    Eq. 4.2; ties go to the lower index in both halves.
    """
    p = v.shape[-1]
    if not 1 <= k <= p:
        msg = f"k = {k} must be in 1..{p}"
        raise ValueError(msg)
    order_desc = torch.sort(v, dim=-1, descending=True, stable=True).indices[..., :k]
    order_asc = torch.sort(v, dim=-1, descending=False, stable=True).indices[..., :k]
    bits = torch.zeros((*v.shape[:-1], 2 * p), dtype=torch.bool, device=v.device)
    bits.scatter_(-1, order_desc, True)
    bits.scatter_(-1, order_asc + p, True)
    return bits


def fuse(codes: list[torch.Tensor]) -> torch.Tensor:
    """Return the bitwise OR of the modality SDRs (Eq. 4.3): the HTM's sensory drive."""
    if not codes:
        msg = "at least one modality SDR is needed"
        raise ValueError(msg)
    out = codes[0].clone()
    for code in codes[1:]:
        out |= code
    return out

"""Procedural surface textures: seeded value noise, bands and bricks, so that every surface looks distinct.

A texture is an albedo image in [0, 1] of ``TEXELS_PER_M`` texels per metre along the surface (u, columns)
and up it (v, rows, row 0 at the surface's base). Each is a deterministic function of its own seed, so a
world can hold thousands of distinct textures and copy one exactly (the ``aliased`` scenario does).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

STYLES = ("noise", "bands", "bricks", "stripes")


def value_noise(rng: np.random.Generator, rows: int, cols: int, cell: float) -> FloatArray:
    """Smooth value noise in [0, 1] on a (rows, cols) texel grid with feature size ``cell`` texels.

    Random values on a lattice of spacing ``cell`` are interpolated with smoothstep weights (bilinear in the
    smoothed fractions), which gives a C¹ surface.
    """
    gy = math.ceil(rows / cell) + 2
    gx = math.ceil(cols / cell) + 2
    grid = rng.random((gy, gx))
    y = np.arange(rows) / cell
    x = np.arange(cols) / cell
    y0 = np.floor(y).astype(np.int64)
    x0 = np.floor(x).astype(np.int64)
    fy = y - y0
    fx = x - x0
    fy = fy * fy * (3.0 - 2.0 * fy)
    fx = fx * fx * (3.0 - 2.0 * fx)
    g00 = grid[y0][:, x0]
    g01 = grid[y0][:, x0 + 1]
    g10 = grid[y0 + 1][:, x0]
    g11 = grid[y0 + 1][:, x0 + 1]
    top = g00 * (1.0 - fx) + g01 * fx
    bottom = g10 * (1.0 - fx) + g11 * fx
    return top * (1.0 - fy[:, None]) + bottom * fy[:, None]


def fractal_noise(rng: np.random.Generator, rows: int, cols: int, cell: float, octaves: int = 3) -> FloatArray:
    """Sum of ``octaves`` value-noise layers (feature size halved and amplitude halved each octave), in [0, 1]."""
    total = np.zeros((rows, cols))
    norm = 0.0
    amplitude = 1.0
    for _ in range(octaves):
        total += amplitude * value_noise(rng, rows, cols, max(cell, 1.0))
        norm += amplitude
        amplitude *= 0.5
        cell *= 0.5
    return total / norm


FLOOR_M = 3.0
"""Storey height of the ``windows`` style."""


def _windows(rng: np.random.Generator, wall: FloatArray, texels_per_m: float) -> FloatArray:
    """Return one façade bay: ``wall`` with a dark, slightly textured window on every storey.

    The window spans a random 35–65 % of the bay's width, centred, from 0.9 m to 0.9 + 1.2–1.7 m above each
    floor; the ground floor's opening reaches down to 0.1 m (a shop front or a door).
    """
    rows, cols = wall.shape
    width = float(rng.uniform(0.35, 0.65))
    sill, tall = 0.9, float(rng.uniform(1.2, 1.7))
    glass = float(rng.uniform(0.05, 0.3))
    v = np.arange(rows)[:, None] / texels_per_m
    u = np.arange(cols)[None, :] / max(cols - 1, 1)
    in_storey = np.mod(v, FLOOR_M)
    bottom = np.where(v < FLOOR_M, 0.1, sill)
    window = (np.abs(u - 0.5) < width / 2) & (in_storey >= bottom) & (in_storey <= sill + tall)
    return np.where(window, glass + 0.15 * wall, 0.4 + 0.5 * wall)


def make_texture(
    seed: int, length_m: float, height_m: float, texels_per_m: float, feature_m: float, style: str | None = None
) -> FloatArray:
    """Return the albedo texture of one surface.

    Args:
        seed: the texture's own seed (same seed, same texture).
        length_m: surface length (u extent).
        height_m: surface height (v extent).
        texels_per_m: resolution.
        feature_m: typical feature size of the pattern (m).
        style: ``noise`` (fractal value noise), ``bands`` (horizontal strata), ``bricks``, ``stripes``
            (vertical bars) or ``windows`` (one bay of a building's façade: a window per floor); None picks
            one of :data:`STYLES` from the seed.

    Returns:
        (rows, cols) float64 albedo in [0.02, 0.98].

    """
    rng = np.random.default_rng(seed)
    rows = max(2, math.ceil(height_m * texels_per_m) + 1)
    cols = max(2, math.ceil(length_m * texels_per_m) + 1)
    if style is None:
        style = STYLES[int(rng.integers(len(STYLES)))]
    cell = feature_m * texels_per_m
    base = float(rng.uniform(0.1, 0.9))
    contrast = float(rng.uniform(0.5, 0.9))
    pattern = fractal_noise(rng, rows, cols, cell * 2.0)
    if style == "bands":
        strata = value_noise(rng, rows, 1, cell * float(rng.uniform(0.4, 1.0)))
        pattern = 0.35 * pattern + 0.65 * np.repeat(strata, cols, axis=1)
    elif style == "bricks":
        brick_h = max(2, int(cell * float(rng.uniform(0.3, 0.6))))
        brick_w = max(3, int(cell * float(rng.uniform(0.8, 1.6))))
        r = np.arange(rows)[:, None]
        c = np.arange(cols)[None, :]
        course = r // brick_h
        col_index = (c + (course % 2) * (brick_w // 2)) // brick_w
        shade = np.random.default_rng(seed + 7).random((int(course.max()) + 1, int(col_index.max()) + 2))
        bricks = shade[course, col_index]
        mortar = ((r % brick_h) == 0) | (((c + (course % 2) * (brick_w // 2)) % brick_w) == 0)
        pattern = np.where(mortar, 0.1, 0.3 * pattern + 0.7 * bricks)
    elif style == "windows":
        pattern = _windows(rng, pattern, texels_per_m)
    elif style == "stripes":
        bars = value_noise(rng, 1, cols, cell * float(rng.uniform(0.3, 0.8)))
        bars = (bars > 0.5).astype(np.float64) * 0.8 + 0.1 * bars
        pattern = 0.4 * pattern + 0.6 * np.repeat(bars, rows, axis=0)
    texture = base + contrast * (pattern - 0.5) * 2.0
    return np.clip(texture, 0.02, 0.98)

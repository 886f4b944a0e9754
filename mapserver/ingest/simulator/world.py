"""The simulated 3-D world: vertical textured surfaces (walls, box faces) standing on a floor.

Geometry is "2.5-D": every surface is a vertical rectangle above a segment ``p0 → p1`` of the ground plane,
from height ``base`` to ``top``, carrying its own texture (:mod:`.textures`). Boxes are four such faces.
A world optionally has a ceiling (a cave's water surface); otherwise the sky is the fog colour. In a world
with a *local floor* (a building's storeys, a terrain's slopes) the floor a camera sees lies at its vehicle's
own height, and with a ``storey`` height the camera sees only the band from that floor to the ceiling
``storey`` metres above it: a storey's camera sees neither the storey below nor the one above.

:class:`WorldBuilder` assembles a world: single walls, boxes, boxes scattered at random off the vehicles'
routes (so every place has its own arrangement of distinct textures), and exact copies of a set of surfaces
at another place (the ``aliased`` and ``twin`` scenarios' look-alike stretches) or rotated about a centre
(the ``symmetric`` scenario). :meth:`WorldBuilder.build` packs
everything into flat numpy arrays for the renderer.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from mapserver.ingest.simulator.routes import Route
from mapserver.ingest.simulator.textures import make_texture

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

LIGHT_DIRECTION = (math.cos(math.radians(35.0)), math.sin(math.radians(35.0)))
"""Horizontal direction of the world's fixed light; a face's brightness depends on its orientation."""

AMBIENT = 0.6
"""Share of a surface's brightness that does not depend on its orientation to the light."""


@dataclass(frozen=True)
class World:
    """Packed world geometry and textures (see the module docstring).

    Attributes:
        p0: (S, 2) segment starts.
        p1: (S, 2) segment ends.
        base: (S,) bottom height of each surface.
        top: (S,) top height.
        shade: (S,) brightness factor from the surface's orientation to the light.
        tex_offset: (S,) start of each surface's texture in :attr:`tex_flat`.
        tex_rows: (S,) texture rows (v, upwards).
        tex_cols: (S,) texture columns (u, along ``p0 → p1``).
        tex_flat: all textures, row-major, concatenated (float32 albedo).
        texels_per_m: texture resolution.
        floor_z: floor height.
        floor_albedo: floor brightness.
        ceiling_z: ceiling height, or None for an open sky.
        ceiling_albedo: ceiling brightness.
        local_floor: the floor a camera sees lies at its vehicle's height (not at ``floor_z``).
        storey: with ``local_floor``, the height of the visible band above that floor, which is also the
            ceiling's height above it (None: no band, the world's ceiling).

    """

    p0: FloatArray
    p1: FloatArray
    base: FloatArray
    top: FloatArray
    shade: FloatArray
    tex_offset: IntArray
    tex_rows: IntArray
    tex_cols: IntArray
    tex_flat: npt.NDArray[np.float32]
    texels_per_m: float
    floor_z: float
    floor_albedo: float
    ceiling_z: float | None
    ceiling_albedo: float
    local_floor: bool = False
    storey: float | None = None
    midpoint: FloatArray = field(init=False)
    half_length: FloatArray = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "midpoint", 0.5 * (self.p0 + self.p1))
        object.__setattr__(self, "half_length", 0.5 * np.linalg.norm(self.p1 - self.p0, axis=1))

    @property
    def count(self) -> int:
        """Return the number of surfaces."""
        return int(self.p0.shape[0])

    def lit(self, turn_rad: float) -> World:
        """Return the world lit from a light turned by ``turn_rad`` from :data:`LIGHT_DIRECTION` (the sun moved)."""
        base = math.atan2(LIGHT_DIRECTION[1], LIGHT_DIRECTION[0]) + turn_rad
        shade = surface_shade(self.p0, self.p1, (math.cos(base), math.sin(base)))
        return dataclasses.replace(self, shade=shade)

    def band(self, z: float) -> tuple[float, float | None, float, float]:
        """Return (floor, ceiling or None, lowest, highest visible height) for a vehicle at height ``z``."""
        if not self.local_floor:
            return self.floor_z, self.ceiling_z, -math.inf, math.inf
        if self.storey is None:
            return z, self.ceiling_z, z, math.inf
        return z, z + self.storey, z, z + self.storey

    def near(self, x: float, y: float, radius: float) -> IntArray:
        """Return the indices of surfaces with a point within ``radius`` of (x, y) (bounding-circle test)."""
        d = np.hypot(self.midpoint[:, 0] - x, self.midpoint[:, 1] - y)
        return np.flatnonzero(d <= radius + self.half_length)


def surface_shade(p0: FloatArray, p1: FloatArray, light: tuple[float, float]) -> FloatArray:
    """Return the brightness factor of each surface ``p0 → p1`` lit from the horizontal direction ``light``.

    ``AMBIENT + (1 − AMBIENT)·|n·l|``: a face turned to the light is brightest, one edge-on to it shows the
    ambient share only.
    """
    edge = p1 - p0
    length = np.maximum(np.linalg.norm(edge, axis=1), 1e-12)
    normal = np.stack([-edge[:, 1], edge[:, 0]], axis=1) / length[:, None]
    return AMBIENT + (1.0 - AMBIENT) * np.abs(normal @ np.asarray(light, dtype=np.float64))


@dataclass
class _Surface:
    p0: tuple[float, float]
    p1: tuple[float, float]
    base: float
    top: float
    texture: int  # index into the builder's texture list


class WorldBuilder:
    """Collects surfaces and textures, then packs them into a :class:`World`.

    Args:
        seed: base seed of the textures (texture ``k`` of the world uses ``seed·1_000_003 + k``).
        texels_per_m: texture resolution.
        feature_m: typical size of texture features (m).
        floor_z: floor height.
        ceiling_z: ceiling height or None (open sky).
        floor_albedo: floor brightness.
        ceiling_albedo: ceiling brightness.
        local_floor: the floor a camera sees lies at its vehicle's height (:class:`World`).
        storey: the visible band's height above that floor (:class:`World`).

    """

    def __init__(
        self,
        seed: int,
        *,
        texels_per_m: float = 10.0,
        feature_m: float = 0.6,
        floor_z: float = 0.0,
        ceiling_z: float | None = None,
        floor_albedo: float = 0.35,
        ceiling_albedo: float = 0.8,
        local_floor: bool = False,
        storey: float | None = None,
    ) -> None:
        self.seed = int(seed)
        self.texels_per_m = float(texels_per_m)
        self.feature_m = float(feature_m)
        self.floor_z = float(floor_z)
        self.ceiling_z = ceiling_z
        self.floor_albedo = float(floor_albedo)
        self.ceiling_albedo = float(ceiling_albedo)
        self.local_floor = bool(local_floor)
        self.storey = None if storey is None else float(storey)
        self.surfaces: list[_Surface] = []
        self.textures: list[npt.NDArray[np.float32]] = []

    # ---------------------------------------------------------------------------------------------- surfaces
    def add_texture(self, length: float, height: float, style: str | None = None) -> int:
        """Make a texture for a surface of ``length`` × ``height`` metres; return its index (for :meth:`add_wall`)."""
        seed = self.seed * 1_000_003 + len(self.textures)
        texture = make_texture(seed, length, height, self.texels_per_m, self.feature_m, style)
        self.textures.append(texture.astype(np.float32))
        return len(self.textures) - 1

    def add_wall(
        self,
        p0: Sequence[float] | np.ndarray,
        p1: Sequence[float] | np.ndarray,
        *,
        top: float,
        base: float | None = None,
        style: str | None = None,
        texture: int | None = None,
    ) -> int:
        """Add one textured vertical wall above the segment ``p0 → p1``; return its surface index.

        ``texture`` reuses a texture made by :meth:`add_texture` (a repeated façade module); by default the
        wall gets a texture of its own.
        """
        lo = self.floor_z if base is None else float(base)
        length = math.hypot(p1[0] - p0[0], p1[1] - p0[1])
        if texture is None:
            texture = self.add_texture(length, top - lo, style)
        self.surfaces.append(_Surface((float(p0[0]), float(p0[1])), (float(p1[0]), float(p1[1])), lo, top, texture))
        return len(self.surfaces) - 1

    def add_polyline(
        self, points: npt.ArrayLike, *, top: float, closed: bool = False, style: str | None = None
    ) -> list[int]:
        """Add a wall along each segment of a polyline (a cave wall, a boundary); return the indices."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        pairs = list(itertools.pairwise(pts))
        if closed:
            pairs.append((pts[-1], pts[0]))
        return [self.add_wall(a, b, top=top, style=style) for a, b in pairs]

    def add_box(
        self, centre: Sequence[float], half_x: float, half_y: float, angle: float, top: float
    ) -> list[int]:
        """Add a box (four faces, counter-clockwise so each face's left normal points inwards).

        Args:
            centre: (x, y) centre.
            half_x: half size along the box's own x axis.
            half_y: half size along its y axis.
            angle: rotation of the box (rad).
            top: height of the box.

        Returns:
            The four surface indices.

        """
        c, s = math.cos(angle), math.sin(angle)
        corners = [(-half_x, -half_y), (half_x, -half_y), (half_x, half_y), (-half_x, half_y)]
        pts = [(centre[0] + c * a - s * b, centre[1] + s * a + c * b) for a, b in corners]
        return [self.add_wall(pts[k], pts[(k + 1) % 4], top=top) for k in range(4)]

    def copy_surfaces(self, indices: Sequence[int], offset: Sequence[float], rise: float = 0.0) -> list[int]:
        """Add exact copies (same textures) of surfaces translated by ``offset`` and raised by ``rise`` metres."""
        out = []
        for k in indices:
            src = self.surfaces[k]
            self.surfaces.append(
                _Surface(
                    (src.p0[0] + offset[0], src.p0[1] + offset[1]),
                    (src.p1[0] + offset[0], src.p1[1] + offset[1]),
                    src.base + rise,
                    src.top + rise,
                    src.texture,
                )
            )
            out.append(len(self.surfaces) - 1)
        return out

    def rotate_copy(self, indices: Sequence[int], centre: Sequence[float], angle: float) -> list[int]:
        """Add exact copies (same textures, same heights) of surfaces rotated by ``angle`` about ``centre``.

        A rotation keeps each surface's orientation (``p0 → p1`` maps to ``p0' → p1'``), so the copy's texture
        runs the same way along it: rotating the viewer with the surfaces gives the same image.
        """
        c, s = math.cos(angle), math.sin(angle)
        cx, cy = float(centre[0]), float(centre[1])

        def turn(p: tuple[float, float]) -> tuple[float, float]:
            dx, dy = p[0] - cx, p[1] - cy
            return (cx + c * dx - s * dy, cy + s * dx + c * dy)

        out = []
        for k in indices:
            src = self.surfaces[k]
            self.surfaces.append(_Surface(turn(src.p0), turn(src.p1), src.base, src.top, src.texture))
            out.append(len(self.surfaces) - 1)
        return out

    def retexture(self, index: int, style: str | None = None) -> None:
        """Give surface ``index`` a new texture of its own (a copy that differs in its details)."""
        surface = self.surfaces[index]
        length = math.hypot(surface.p1[0] - surface.p0[0], surface.p1[1] - surface.p0[1])
        surface.texture = self.add_texture(length, surface.top - surface.base, style)

    def raise_surfaces(self, indices: Sequence[int], heights: Sequence[float]) -> None:
        """Raise surface ``indices[k]`` (base and top) by ``heights[k]`` metres (walls standing on a slope)."""
        for k, rise in zip(indices, heights, strict=True):
            self.surfaces[k].base += float(rise)
            self.surfaces[k].top += float(rise)

    def remove(self, indices: Sequence[int]) -> None:
        """Remove surfaces (their textures stay in the list, unused); later indices shift down."""
        drop = set(indices)
        self.surfaces = [surface for k, surface in enumerate(self.surfaces) if k not in drop]

    def midpoints(self) -> FloatArray:
        """Return the (S, 2) midpoints of the surfaces added so far."""
        if not self.surfaces:
            return np.zeros((0, 2))
        return np.array([[(s.p0[0] + s.p1[0]) / 2, (s.p0[1] + s.p1[1]) / 2] for s in self.surfaces])

    def scatter_boxes(
        self,
        rng: np.random.Generator,
        keep_clear: npt.ArrayLike,
        bounds: tuple[float, float, float, float],
        *,
        density: float,
        clearance: float,
        size: tuple[float, float] = (0.4, 1.6),
        height: tuple[float, float] = (1.2, 4.0),
        exclude: Sequence[tuple[float, float, float]] = (),
        inside: tuple[float, float, float] | None = None,
    ) -> list[list[int]]:
        """Scatter boxes at random, keeping ``clearance`` metres from every point of ``keep_clear``.

        Args:
            rng: random generator (placement, sizes, heights).
            keep_clear: (M, 2) points the boxes must stay away from (the routes, densely sampled).
            bounds: (x_min, y_min, x_max, y_max) of the area to fill.
            density: boxes per square metre tried (rejected candidates are not replaced).
            clearance: minimum distance from a box's bounding circle to ``keep_clear``.
            size: range of the half sizes (m).
            height: range of the heights (m above the floor).
            exclude: discs (x, y, r) no box may touch.
            inside: a disc (x, y, r) every box must lie within, or None.

        Returns:
            The surface indices of each box placed.

        """
        x0, y0, x1, y1 = bounds
        tries = int(density * (x1 - x0) * (y1 - y0))
        tree = cKDTree(np.asarray(keep_clear, dtype=np.float64).reshape(-1, 2))
        placed: list[tuple[float, float, float]] = []
        boxes: list[list[int]] = []
        for _ in range(tries):
            cx, cy = float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1))
            hx, hy = float(rng.uniform(*size)), float(rng.uniform(*size))
            angle = float(rng.uniform(0.0, math.pi))
            top = self.floor_z + float(rng.uniform(*height))
            radius = math.hypot(hx, hy)
            distance, _ = tree.query((cx, cy))
            if distance < clearance + radius:
                continue
            if any(math.hypot(cx - ex, cy - ey) < er + radius for ex, ey, er in exclude):
                continue
            if inside is not None and math.hypot(cx - inside[0], cy - inside[1]) > inside[2] - radius:
                continue
            if any(math.hypot(cx - px, cy - py) < pr + radius + 0.3 for px, py, pr in placed):
                continue
            placed.append((cx, cy, radius))
            boxes.append(self.add_box((cx, cy), hx, hy, angle, top))
        return boxes

    def scatter_walls(
        self,
        rng: np.random.Generator,
        keep_clear: npt.ArrayLike,
        bounds: tuple[float, float, float, float],
        *,
        density: float,
        clearance: float,
        length: tuple[float, float] = (1.0, 4.0),
        height: tuple[float, float] = (0.8, 3.5),
        exclude: Sequence[tuple[float, float, float]] = (),
    ) -> list[int]:
        """Scatter free-standing walls of random length, orientation, height and texture.

        A wall with a point closer than ``clearance`` to ``keep_clear`` or touching an ``exclude`` disc is
        not placed; walls may cross each other.

        Args:
            rng: random generator.
            keep_clear: (M, 2) points walls must stay away from.
            bounds: (x_min, y_min, x_max, y_max) of the wall centres.
            density: walls tried per square metre.
            clearance: minimum distance to ``keep_clear`` (m).
            length: range of wall lengths (m).
            height: range of wall heights (m).
            exclude: discs (x, y, r) no wall may touch.

        Returns:
            The surface indices added.

        """
        x0, y0, x1, y1 = bounds
        tries = int(density * (x1 - x0) * (y1 - y0))
        tree = cKDTree(np.asarray(keep_clear, dtype=np.float64).reshape(-1, 2))
        added: list[int] = []
        for _ in range(tries):
            cx, cy = float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1))
            half = 0.5 * float(rng.uniform(*length))
            angle = float(rng.uniform(0.0, math.pi))
            top = self.floor_z + float(rng.uniform(*height))
            a = (cx - half * math.cos(angle), cy - half * math.sin(angle))
            b = (cx + half * math.cos(angle), cy + half * math.sin(angle))
            samples = np.linspace(a, b, max(2, math.ceil(2 * half / 0.2) + 1))
            near, _ = tree.query(samples)
            if np.any(near < clearance):
                continue
            if any(math.hypot(cx - ex, cy - ey) < er + half for ex, ey, er in exclude):
                continue
            added.append(self.add_wall(a, b, top=top))
        return added

    def line_route(
        self,
        rng: np.random.Generator,
        route_xy: npt.ArrayLike,
        keep_clear: npt.ArrayLike,
        *,
        offset: float | tuple[float, float],
        clearance: float,
        panel: tuple[float, float] = (1.5, 4.0),
        gap: tuple[float, float] = (0.2, 1.5),
        height: tuple[float, float] = (1.5, 3.5),
        closed: bool = True,
    ) -> list[int]:
        """Line a route on both sides with wall panels ``offset`` metres from it (a corridor of façades).

        Panels of random length, height and texture alternate with random gaps (doorways through which
        the scene behind shows). A panel with any point closer than ``clearance`` to ``keep_clear`` (every
        route of the world) is left out, so corridors never block a crossing or a neighbouring route.

        Args:
            rng: random generator.
            route_xy: (N, 2) dense vertices of the route (a few centimetres apart).
            keep_clear: (M, 2) points panels must stay away from.
            offset: distance of the panels from the route (m), or a range to draw each panel's from.
            clearance: minimum distance of a panel from ``keep_clear``.
            panel: range of panel lengths (m, measured along the route).
            gap: range of gap lengths (m).
            height: range of panel heights (m).
            closed: the route is a loop.

        Returns:
            The indices of the panels added.

        """
        pts = np.asarray(route_xy, dtype=np.float64).reshape(-1, 2)
        if closed:
            pts = np.vstack([pts, pts[:1]])
        d = np.diff(pts, axis=0)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(d, axis=1))])
        heading = np.arctan2(d[:, 1], d[:, 0])
        heading = np.concatenate([heading, heading[-1:]])
        normal = np.stack([-np.sin(heading), np.cos(heading)], axis=1)
        tree = cKDTree(np.asarray(keep_clear, dtype=np.float64).reshape(-1, 2))
        added: list[int] = []
        for side in (1.0, -1.0):
            pos = float(rng.uniform(0.0, gap[1]))
            while pos < s[-1]:
                length = float(rng.uniform(*panel))
                end = min(pos + length, float(s[-1]))
                top = self.floor_z + float(rng.uniform(*height))
                dist = float(rng.uniform(*offset)) if isinstance(offset, tuple) else float(offset)
                samples = np.linspace(pos, end, max(2, math.ceil((end - pos) / 0.25) + 1))
                idx = np.clip(np.searchsorted(s, samples), 0, len(s) - 1)
                wall = pts[idx] + side * dist * normal[idx]
                near, _ = tree.query(wall)
                if np.all(near >= min(clearance, dist - 0.3)) and end - pos > 0.5:
                    for a, b in itertools.pairwise(wall):
                        added.append(self.add_wall(a, b, top=top))
                pos = end + float(rng.uniform(*gap))
        return added

    def facades(
        self,
        rng: np.random.Generator,
        route: Route,
        keep_clear: npt.ArrayLike,
        *,
        offset: float,
        palette: Sequence[int],
        module_m: float,
        modules: tuple[int, int],
        gap: tuple[float, float],
        height: tuple[float, float],
    ) -> list[int]:
        """Line a closed route on both sides with buildings whose façades repeat one module (a street).

        A building is ``modules`` (a range) façade modules side by side, each a wall ``module_m`` metres long
        (a chord of the offset route) showing the same texture, one of ``palette`` (indices from
        :meth:`add_texture`), drawn per building; so a façade repeats along a building, and buildings of one
        texture repeat along the street. Buildings are ``gap`` metres apart (side streets, through which the
        scene behind shows) and of random height. A module with a point closer than ``offset − 0.3`` m to
        ``keep_clear`` (any route of the world: the inside of a tight corner, a crossing street) is left out.

        Returns:
            The indices of the walls added.

        """
        tree = cKDTree(np.asarray(keep_clear, dtype=np.float64).reshape(-1, 2))
        added: list[int] = []
        for side in (1.0, -1.0):
            pos = float(rng.uniform(0.0, gap[1]))
            while pos < route.length - module_m:
                count = int(rng.integers(modules[0], modules[1] + 1))
                texture = int(palette[int(rng.integers(len(palette)))])
                top = self.floor_z + float(rng.uniform(*height))
                starts = pos + module_m * np.arange(count)
                starts = starts[starts + module_m <= route.length]
                ends = starts + module_m
                a = route.position(starts) + side * offset * route.normal(starts)
                b = route.position(ends) + side * offset * route.normal(ends)
                near_a, _ = tree.query(a)
                near_b, _ = tree.query(b)
                for k in np.flatnonzero((near_a >= offset - 0.3) & (near_b >= offset - 0.3)):
                    p, q = (a[k], b[k]) if side < 0 else (b[k], a[k])  # the texture reads left to right from the street
                    added.append(self.add_wall(p, q, top=top, texture=texture))
                pos = float(ends[-1]) + float(rng.uniform(*gap)) if ends.size else route.length
        return added

    # ---------------------------------------------------------------------------------------------- packing
    def build(self) -> World:
        """Pack the surfaces and textures into a :class:`World`."""
        n = len(self.surfaces)
        p0 = np.array([s.p0 for s in self.surfaces], dtype=np.float64).reshape(n, 2)
        p1 = np.array([s.p1 for s in self.surfaces], dtype=np.float64).reshape(n, 2)
        shade = surface_shade(p0, p1, LIGHT_DIRECTION)
        sizes = [t.size for t in self.textures]
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64) if sizes else np.zeros(0, np.int64)
        tex = np.array([s.texture for s in self.surfaces], dtype=np.int64)
        flat = np.concatenate([t.reshape(-1) for t in self.textures]) if self.textures else np.zeros(0, np.float32)
        rows = np.array([t.shape[0] for t in self.textures], dtype=np.int64)
        cols = np.array([t.shape[1] for t in self.textures], dtype=np.int64)
        return World(
            p0=p0,
            p1=p1,
            base=np.array([s.base for s in self.surfaces], dtype=np.float64),
            top=np.array([s.top for s in self.surfaces], dtype=np.float64),
            shade=shade,
            tex_offset=starts[tex] if n else np.zeros(0, np.int64),
            tex_rows=rows[tex] if n else np.zeros(0, np.int64),
            tex_cols=cols[tex] if n else np.zeros(0, np.int64),
            tex_flat=flat.astype(np.float32),
            texels_per_m=self.texels_per_m,
            floor_z=self.floor_z,
            floor_albedo=self.floor_albedo,
            ceiling_z=self.ceiling_z,
            ceiling_albedo=self.ceiling_albedo,
            local_floor=self.local_floor,
            storey=self.storey,
        )

"""A vectorised ray caster: the camera image of a :class:`~.world.World` seen from a vehicle pose.

Projection is cylindrical: image column ``j`` looks along the azimuth ``yaw + hfov/2 − (j + ½)·hfov/W``
(column 0 on the left), image row ``i`` along the elevation whose tangent is ``(H/2 − i − ½)/f`` with
``f = W/hfov`` pixels per radian, so pixels are square at the horizon (or ``f = (H/2)/tan(vfov/2)`` when a
vertical field of view is given). With ``hfov = 360°`` this is a
panoramic camera, and turning the vehicle shifts the image columns.

Per column one horizontal ray is intersected with every surface near the camera (2-D segment
intersection, all columns and surfaces at once); the ``HITS`` nearest hits are kept. A pixel shows the
nearest of them whose surface spans the height ``z_cam + t·tan(elevation)`` at the hit distance ``t``, so
the camera height decides which part of a wall's texture is seen and a short box does not hide a tall one
behind it. Rows that hit no surface show the floor, the ceiling, or the sky (fog colour). In a world with a
local floor (:meth:`~.world.World.band`) the floor lies at the vehicle's height and a hit counts only within
the visible band above it (a building's storey).

Shading: ``albedo · shade`` (the surface's orientation to the world light), then fog
``I·a + fog·(1 − a)`` with ``a = exp(−r/fog_length)`` faded to 0 over the last ``fade`` metres before
``max_range`` (r: 3-D distance), which also bounds what a camera can see: nothing beyond ``max_range``.
Sensor effects (lighting gain, pixel noise, quantisation) are applied by :func:`expose`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import numpy.typing as npt
from scipy.ndimage import gaussian_filter1d

from mapserver.ingest.simulator.world import World

FloatArray = npt.NDArray[np.float64]

HITS = 6
"""Nearest surface hits kept per column."""


@dataclass(frozen=True)
class Camera:
    """Camera model and visibility.

    Attributes:
        width: image columns.
        height: image rows.
        hfov_deg: horizontal field of view (360 for a panoramic camera).
        vfov_deg: vertical field of view, or None for square pixels at the horizon.
        mount_height: camera height above the vehicle's reference point (m).
        fog_length: distance over which contrast falls by 1/e (m).
        max_range: nothing farther than this is visible (m).
        fade: width of the fade to fog before ``max_range`` (m).
        fog_level: brightness of the fog and the sky, 0..1.
        blur_px: standard deviation of the horizontal blur (Gaussian, pixels; wraps around a panorama):
            optics plus the motion blur of a moving, turning vehicle.
        vblur_px: standard deviation of the vertical blur, or None for ``blur_px``.

    """

    width: int = 256
    height: int = 64
    hfov_deg: float = 360.0
    vfov_deg: float | None = None
    mount_height: float = 1.0
    fog_length: float = 12.0
    max_range: float = 10.0
    fade: float = 2.0
    fog_level: float = 0.55
    blur_px: float = 0.0
    vblur_px: float | None = None
    azimuths: FloatArray = field(init=False, repr=False)
    slopes: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        hfov = math.radians(self.hfov_deg)
        j = np.arange(self.width, dtype=np.float64)
        object.__setattr__(self, "azimuths", hfov / 2.0 - (j + 0.5) * hfov / self.width)
        focal = self.width / hfov
        if self.vfov_deg is not None:
            focal = self.height / 2.0 / math.tan(math.radians(self.vfov_deg) / 2.0)
        i = np.arange(self.height, dtype=np.float64)
        object.__setattr__(self, "slopes", (self.height / 2.0 - i - 0.5) / focal)


@dataclass(frozen=True)
class Lighting:
    """How the light changes during a session, so that a place seen again a lap later looks different.

    Attributes:
        turn_rad_per_s: the sun's horizontal direction turns this fast (faces turned to it brighten, others
            darken: :meth:`~.world.World.lit`).
        gain_per_s: the exposure changes by this fraction of its starting value per second (dusk: < 0),
            never below a quarter of it.

    """

    turn_rad_per_s: float = 0.0
    gain_per_s: float = 0.0

    def at(self, world: World, t: float) -> tuple[World, float]:
        """Return the world as lit ``t`` seconds into the session, and the exposure factor then."""
        lit = world.lit(self.turn_rad_per_s * t) if self.turn_rad_per_s else world
        return lit, max(0.25, 1.0 + self.gain_per_s * t)


def _attenuation(camera: Camera, r: FloatArray) -> FloatArray:
    fade = np.clip((camera.max_range - r) / max(camera.fade, 1e-9), 0.0, 1.0)
    return np.exp(-r / camera.fog_length) * fade


@dataclass(frozen=True)
class SurfaceHits:
    """The nearest surface each ray (elevation row × azimuth column) meets within range.

    Attributes:
        covered: (H, W) whether the ray meets a surface.
        rows, cols: the covered rays' indices.
        surface: the surface each covered ray meets.
        t: horizontal distance to the hit (m).
        u_m: metres along the surface from its start.
        z: the height of the hit.
    """

    covered: npt.NDArray[np.bool_]
    rows: npt.NDArray[np.int64]
    cols: npt.NDArray[np.int64]
    surface: npt.NDArray[np.int64]
    t: FloatArray
    u_m: FloatArray
    z: FloatArray


def surface_hits(
    world: World, x: float, y: float, cz: float, azimuths: FloatArray, slopes: FloatArray, max_range: float,
    band: tuple[float, float] = (-math.inf, math.inf),
) -> SurfaceHits:
    """Intersect the rays from (x, y, cz) along ``azimuths`` (W,) and elevation ``slopes`` (H,) with the surfaces.

    Per column one horizontal ray is intersected with every surface within ``max_range`` (2-D segment
    intersection, all columns and surfaces at once); of its ``HITS`` nearest hits a ray of slope ``h`` meets
    the nearest whose surface spans the height ``cz + t·h`` at the hit distance ``t``, that height inside
    ``band`` (lowest, highest).
    """
    dx, dy = np.cos(azimuths), np.sin(azimuths)
    height_px, width_px = slopes.shape[0], azimuths.shape[0]
    empty = np.zeros(0, dtype=np.int64)
    sel = world.near(x, y, max_range)
    if not sel.size:
        none = np.zeros(0)
        return SurfaceHits(np.zeros((height_px, width_px), dtype=bool), empty, empty, empty, none, none, none)
    p0 = world.p0[sel]
    edge = world.p1[sel] - p0
    ox = p0[:, 0] - x
    oy = p0[:, 1] - y
    denom = dx[:, None] * edge[None, :, 1] - dy[:, None] * edge[None, :, 0]  # cross(d, e): (W, S)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ox * edge[:, 1] - oy * edge[:, 0])[None, :] / denom
        u = (ox[None, :] * dy[:, None] - oy[None, :] * dx[:, None]) / denom
    ok = (np.abs(denom) > 1e-12) & (t > 1e-6) & (u >= 0.0) & (u <= 1.0) & (t < max_range)
    t = np.where(ok, t, np.inf)
    k = min(HITS, sel.size)
    nearest = np.argpartition(t, k - 1, axis=1)[:, :k] if k < sel.size else np.argsort(t, axis=1)
    t_k = np.take_along_axis(t, nearest, axis=1)
    order = np.argsort(t_k, axis=1)
    nearest = np.take_along_axis(nearest, order, axis=1)[:, :k]  # (W, k) local surface index
    t_k = np.take_along_axis(t_k, order, axis=1)[:, :k]
    u_k = np.take_along_axis(u, nearest, axis=1)
    surf = sel[nearest]  # (W, k)
    finite = np.isfinite(t_k)
    z_hit = cz + np.where(finite, t_k, 0.0)[None, :, :] * slopes[:, None, None]  # (H, W, k)
    lo = np.maximum(world.base[surf], band[0])[None]
    hi = np.minimum(world.top[surf], band[1])[None]
    spans = (z_hit >= lo) & (z_hit <= hi) & finite[None]
    covered = np.asarray(spans.any(axis=2))
    rows_c, cols_c = np.nonzero(covered)
    first = np.argmax(spans[rows_c, cols_c], axis=1)  # nearest surface spanning the ray's height
    s_px = surf[cols_c, first]
    return SurfaceHits(
        covered, rows_c, cols_c, s_px, t_k[cols_c, first], u_k[cols_c, first] * world.half_length[s_px] * 2.0,
        z_hit[rows_c, cols_c, first],
    )


def render(world: World, camera: Camera, x: float, y: float, z: float, yaw: float) -> FloatArray:
    """Render the radiance image (H, W) in [0, 1] seen from vehicle pose (x, y, z, yaw).

    Args:
        world: the scene.
        camera: camera model; the camera sits ``mount_height`` above (x, y, z).
        x: vehicle x (m).
        y: vehicle y (m).
        z: vehicle z (m).
        yaw: vehicle heading (rad); the image centre column looks along it.

    Returns:
        float64 image, row 0 at the top.

    """
    cz = z + camera.mount_height
    h = camera.slopes  # (H,)
    az = yaw + camera.azimuths  # (W,)
    height_px, width_px = h.shape[0], az.shape[0]
    image = np.empty((height_px, width_px))
    floor_z, ceiling_z, lowest, highest = world.band(z)
    hits = surface_hits(world, x, y, cz, az, h, camera.max_range, (lowest, highest))
    covered = hits.covered
    if hits.rows.size:
        albedo = _sample(world, hits.surface, hits.u_m, hits.z - world.base[hits.surface])
        radiance = albedo * world.shade[hits.surface]
        r = hits.t * np.sqrt(1.0 + h[hits.rows] ** 2)
        a = _attenuation(camera, r)
        image[hits.rows, hits.cols] = radiance * a + camera.fog_level * (1.0 - a)

    rest = ~covered
    if rest.any():
        slope = np.broadcast_to(h[:, None], (height_px, width_px))
        level = np.full((height_px, width_px), camera.fog_level)
        with np.errstate(divide="ignore", invalid="ignore"):
            down = slope < 0.0
            d_floor = (cz - floor_z) / -slope
            r_floor = d_floor * np.sqrt(1.0 + slope**2)
            a = _attenuation(camera, np.where(down, r_floor, np.inf))
            level = np.where(down, world.floor_albedo * a + camera.fog_level * (1.0 - a), level)
            if ceiling_z is not None:
                up = slope > 0.0
                d_ceiling = (ceiling_z - cz) / slope
                r_ceiling = d_ceiling * np.sqrt(1.0 + slope**2)
                a = _attenuation(camera, np.where(up, r_ceiling, np.inf))
                level = np.where(up, world.ceiling_albedo * a + camera.fog_level * (1.0 - a), level)
        image[rest] = level[rest]
    if camera.blur_px > 0.0 or (camera.vblur_px or 0.0) > 0.0:
        wrap: Literal["wrap", "nearest"] = "wrap" if camera.hfov_deg >= 360.0 else "nearest"
        if camera.blur_px > 0.0:
            image = gaussian_filter1d(image, camera.blur_px, axis=1, mode=wrap)
        vertical = camera.blur_px if camera.vblur_px is None else camera.vblur_px
        if vertical > 0.0:
            image = gaussian_filter1d(image, vertical, axis=0, mode="nearest")
    return image


def _sample(world: World, surf: npt.NDArray[np.int64], u_m: FloatArray, v_m: FloatArray) -> FloatArray:
    """Bilinear texture lookup of surfaces ``surf`` at (u, v) metres from their lower start corner."""
    rows = world.tex_rows[surf]
    cols = world.tex_cols[surf]
    fu = np.clip(u_m * world.texels_per_m, 0.0, cols - 1.000001)
    fv = np.clip(v_m * world.texels_per_m, 0.0, rows - 1.000001)
    u0 = fu.astype(np.int64)
    v0 = fv.astype(np.int64)
    wu = fu - u0
    wv = fv - v0
    base = world.tex_offset[surf] + v0 * cols + u0
    flat = world.tex_flat
    t00 = flat[base]
    t01 = flat[base + 1]
    t10 = flat[base + cols]
    t11 = flat[base + cols + 1]
    top = t00 * (1.0 - wu) + t01 * wu
    bottom = t10 * (1.0 - wu) + t11 * wu
    return top * (1.0 - wv) + bottom * wv


def expose(radiance: FloatArray, gain: float, noise_sigma: float, rng: np.random.Generator) -> npt.NDArray[np.uint8]:
    """Turn radiance into an 8-bit image: lighting ``gain``, Gaussian pixel noise (grey levels), rounding."""
    values = radiance * (255.0 * gain)
    if noise_sigma > 0.0:
        values = values + rng.normal(0.0, noise_sigma, size=values.shape)
    return np.clip(np.rint(values), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class Sonar:
    """A forward-looking imaging sonar: echo intensity by range (rows) and bearing (columns).

    A fan of ``beams`` bearings over ``hfov_deg`` (column 0 on the left, as the camera), each beam
    ``vfov_deg`` high, sampled by ``elevation_rays`` rays. A ray's echo comes from the nearest surface it
    meets (a wall, a box, the floor or the ceiling) within ``max_range``: backscatter ``albedo · |cos i|``
    (``i`` the angle between the ray and the surface normal; the surface's texture stands for its
    roughness), put into the range bin of the hit's 3-D distance; a beam's bins sum its rays' echoes. Sound
    does not fade in turbid water as light does: the fog of the camera does not apply. Speckle (a
    multiplicative gamma noise of mean 1) and quantisation are applied by :func:`expose_sonar`.

    Attributes:
        beams: image columns (bearings).
        bins: image rows (range bins; row 0 is the farthest, as a sonar display's top).
        hfov_deg: horizontal aperture.
        vfov_deg: vertical aperture of each beam.
        elevation_rays: rays per beam across the vertical aperture.
        max_range: range of the last bin (m).
        mount_height: sonar height above the vehicle's reference point (m).
        speckle_looks: the gamma speckle's shape (higher: less speckle).
        gain: echo to grey level scale (1: a perpendicular white wall filling a beam in one bin is 255).
    """

    beams: int = 64
    bins: int = 48
    hfov_deg: float = 130.0
    vfov_deg: float = 20.0
    elevation_rays: int = 8
    max_range: float = 5.0
    mount_height: float = 0.0
    speckle_looks: float = 4.0
    gain: float = 2.0
    azimuths: FloatArray = field(init=False, repr=False, compare=False)
    slopes: FloatArray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        hfov = math.radians(self.hfov_deg)
        j = np.arange(self.beams, dtype=np.float64)
        object.__setattr__(self, "azimuths", hfov / 2.0 - (j + 0.5) * hfov / self.beams)
        half = math.radians(self.vfov_deg) / 2.0
        angles = -half + (np.arange(self.elevation_rays, dtype=np.float64) + 0.5) * (2.0 * half / self.elevation_rays)
        object.__setattr__(self, "slopes", np.tan(angles[::-1]))


def render_sonar(world: World, sonar: Sonar, x: float, y: float, z: float, yaw: float) -> FloatArray:
    """Return the sonar's echo image (bins, beams) seen from vehicle pose (x, y, z, yaw) (see :class:`Sonar`)."""
    cz = z + sonar.mount_height
    h = sonar.slopes
    az = yaw + sonar.azimuths
    hits = surface_hits(world, x, y, cz, az, h, sonar.max_range)
    rays = h.shape[0]
    echo = np.zeros((rays, az.shape[0]))
    r = np.full((rays, az.shape[0]), np.inf)
    if hits.rows.size:
        albedo = _sample(world, hits.surface, hits.u_m, hits.z - world.base[hits.surface])
        edge = world.p1[hits.surface] - world.p0[hits.surface]
        along = np.cos(az[hits.cols]) * edge[:, 1] - np.sin(az[hits.cols]) * edge[:, 0]
        cos_i = np.abs(along) / np.maximum(np.linalg.norm(edge, axis=1), 1e-12) / np.sqrt(1.0 + h[hits.rows] ** 2)
        echo[hits.rows, hits.cols] = albedo * cos_i
        r[hits.rows, hits.cols] = hits.t * np.sqrt(1.0 + h[hits.rows] ** 2)
    rest = ~hits.covered
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = np.broadcast_to(h[:, None], echo.shape)
        sine = np.abs(slope) / np.sqrt(1.0 + slope**2)  # |cos i| of a horizontal plane
        floor = rest & (slope < 0.0)
        r = np.where(floor, (cz - world.floor_z) / sine, r)
        echo = np.where(floor, world.floor_albedo * sine, echo)
        if world.ceiling_z is not None:
            ceiling = rest & (slope > 0.0)
            r = np.where(ceiling, (world.ceiling_z - cz) / sine, r)
            echo = np.where(ceiling, world.ceiling_albedo * sine, echo)
    inside = np.isfinite(r) & (r < sonar.max_range)
    bins = np.minimum((r[inside] / sonar.max_range * sonar.bins).astype(np.int64), sonar.bins - 1)
    image = np.zeros((sonar.bins, az.shape[0]))
    np.add.at(image, (sonar.bins - 1 - bins, np.nonzero(inside)[1]), echo[inside] / rays)
    return image


def expose_sonar(echo: FloatArray, sonar: Sonar, rng: np.random.Generator) -> npt.NDArray[np.uint8]:
    """Turn an echo image into an 8-bit sonar image: gamma speckle of mean 1, ``gain``, rounding."""
    speckle = rng.gamma(sonar.speckle_looks, 1.0 / sonar.speckle_looks, size=echo.shape)
    return np.clip(np.rint(echo * speckle * (255.0 * sonar.gain)), 0, 255).astype(np.uint8)

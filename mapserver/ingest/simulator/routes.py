"""Routes: planar curves parameterised by arc length, the paths simulated vehicles follow.

A :class:`Route` is a dense polyline (vertices a few centimetres apart) with cumulative arc length ``s``.
Positions between vertices are interpolated linearly, headings (the unwrapped tangent angle) linearly, so
``heading(s)`` is continuous along the route. A closed route wraps ``s`` modulo its length, so a session
may run several laps. Builders cover the scenario shapes: ellipses, rounded rectangles, figure-eights and
turtle paths (straight segments and circular arcs from a start pose), and :func:`concat` joins pieces.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

VERTEX_SPACING_M = 0.02
"""Target distance between the vertices of a built route."""


@dataclass(frozen=True)
class Route:
    """A planar curve with arc-length parameterisation.

    Attributes:
        xy: (N, 2) vertices.
        s: (N,) cumulative arc length at each vertex, ``s[0] == 0``.
        theta: (N,) unwrapped tangent heading at each vertex (rad).
        closed: whether the last vertex joins the first (``s`` then wraps modulo :attr:`length`).

    """

    xy: FloatArray
    s: FloatArray
    theta: FloatArray
    closed: bool

    @property
    def length(self) -> float:
        """Return the total arc length (m)."""
        return float(self.s[-1])

    def _param(self, s: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Return (s wrapped or clipped, number of whole laps) for query arc lengths."""
        q = np.asarray(s, dtype=np.float64)
        if self.closed:
            laps = np.floor(q / self.length)
            return q - laps * self.length, laps
        return np.clip(q, 0.0, self.length), np.zeros_like(q)

    def position(self, s: npt.ArrayLike) -> FloatArray:
        """Return (..., 2) positions at arc lengths ``s`` (wrapped on closed routes, clipped otherwise)."""
        q, _ = self._param(s)
        x = np.interp(q, self.s, self.xy[:, 0])
        y = np.interp(q, self.s, self.xy[:, 1])
        return np.stack([x, y], axis=-1)

    def heading(self, s: npt.ArrayLike) -> FloatArray:
        """Return the tangent heading (rad) at ``s``, continuous across laps (each lap adds the turn)."""
        q, laps = self._param(s)
        turn = float(self.theta[-1] - self.theta[0]) if self.closed else 0.0
        return np.interp(q, self.s, self.theta) + laps * turn

    def normal(self, s: npt.ArrayLike) -> FloatArray:
        """Return (..., 2) unit left normals at ``s``."""
        th = self.heading(s)
        return np.stack([-np.sin(th), np.cos(th)], axis=-1)

    def points(self, spacing: float = 0.25) -> FloatArray:
        """Return (M, 2) points spaced about ``spacing`` metres along the route (for distance queries)."""
        count = max(2, math.ceil(self.length / spacing) + 1)
        return self.position(np.linspace(0.0, self.length, count))


def from_points(xy: npt.ArrayLike, closed: bool) -> Route:
    """Build a route from dense vertices (consecutive duplicates removed).

    Args:
        xy: (N, 2) vertices, a few centimetres apart; for a closed route the first vertex is not repeated.
        closed: join the last vertex to the first.

    Returns:
        The route; for a closed route the first vertex is appended at the end so that ``s`` covers the lap.

    """
    pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if closed:
        pts = np.vstack([pts, pts[:1]])
    step = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    keep = np.concatenate([[True], step > 1e-9])
    pts = pts[keep]
    step = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(step)])
    d = np.diff(pts, axis=0)
    seg = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    # vertex headings: mean of the adjacent segment headings (ends: the end segment)
    theta = np.empty(pts.shape[0])
    theta[0] = seg[0]
    theta[-1] = seg[-1]
    theta[1:-1] = 0.5 * (seg[:-1] + seg[1:])
    if closed:
        full = 2.0 * math.pi * round(float(seg[-1] - seg[0]) / (2.0 * math.pi))  # total turn of one lap
        theta[0] = 0.5 * (seg[-1] - full + seg[0])
        theta[-1] = theta[0] + full
    return Route(xy=pts, s=s, theta=theta, closed=closed)


def ellipse(centre: Sequence[float], a: float, b: float, start_deg: float = 0.0, ccw: bool = True) -> Route:
    """Closed ellipse with semi-axes ``a`` (x) and ``b`` (y), starting at parametric angle ``start_deg``."""
    n = max(64, int(2.0 * math.pi * max(a, b) / VERTEX_SPACING_M))
    sign = 1.0 if ccw else -1.0
    t = math.radians(start_deg) + sign * np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    return from_points(np.stack([centre[0] + a * np.cos(t), centre[1] + b * np.sin(t)], axis=1), closed=True)


def figure_eight(centre: Sequence[float], a: float, b: float) -> Route:
    """Closed figure-eight (lemniscate of Gerono, ``x = a·sin t``, ``y = b·sin t·cos t``) through ``centre``."""
    n = max(128, int(4.0 * math.pi * max(a, b) / VERTEX_SPACING_M))
    t = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    return from_points(
        np.stack([centre[0] + a * np.sin(t), centre[1] + b * np.sin(t) * np.cos(t)], axis=1), closed=True
    )


def turtle(start: Sequence[float], heading_deg: float, moves: Sequence[tuple[str, float, float]]) -> Route:
    """Open route of straight segments and circular arcs driven from a start pose.

    Args:
        start: (x, y) start position.
        heading_deg: start heading.
        moves: ``("line", length, 0)`` or ``("arc", radius, angle_deg)`` (positive angle: left turn).

    Returns:
        The open route.

    """
    x, y = float(start[0]), float(start[1])
    th = math.radians(heading_deg)
    pts = [(x, y)]
    for kind, p1, p2 in moves:
        if kind == "line":
            n = max(1, math.ceil(p1 / VERTEX_SPACING_M))
            for k in range(1, n + 1):
                pts.append((x + math.cos(th) * p1 * k / n, y + math.sin(th) * p1 * k / n))
            x, y = pts[-1]
        elif kind == "arc":
            radius, angle = p1, math.radians(p2)
            n = max(2, math.ceil(abs(angle) * radius / VERTEX_SPACING_M))
            sign = 1.0 if angle >= 0 else -1.0
            cx, cy = x - sign * radius * math.sin(th), y + sign * radius * math.cos(th)
            for k in range(1, n + 1):
                a = th + angle * k / n
                pts.append((cx + sign * radius * math.sin(a), cy - sign * radius * math.cos(a)))
            x, y = pts[-1]
            th += angle
        else:
            msg = f"unknown turtle move {kind!r}"
            raise ValueError(msg)
    return from_points(np.asarray(pts), closed=False)


def closed_turtle(start: Sequence[float], heading_deg: float, moves: Sequence[tuple[str, float, float]]) -> Route:
    """Closed route from turtle moves that return to the start pose (checked to 1 mm)."""
    open_route = turtle(start, heading_deg, moves)
    gap = float(np.linalg.norm(open_route.xy[-1] - open_route.xy[0]))
    if gap > 1e-3:
        msg = f"turtle moves do not close the loop (gap {gap:.4f} m)"
        raise ValueError(msg)
    return from_points(open_route.xy[:-1], closed=True)


def rounded_rectangle(
    centre: Sequence[float], width: float, height: float, radius: float, start: str = "bottom"
) -> Route:
    """Closed counter-clockwise rounded rectangle, starting at the middle of side ``start`` (bottom, right...).

    Args:
        centre: (x, y) centre.
        width: outer width along x.
        height: outer height along y.
        radius: corner radius (less than half of each side).
        start: side whose middle is the start: ``bottom`` (heading east), ``right`` (north), ``top``, ``left``.

    """
    w, h, r = float(width), float(height), float(radius)
    sides = {"bottom": (w, h), "right": (h, w), "top": (w, h), "left": (h, w)}
    first, second = sides[start]
    heading = {"bottom": 0.0, "right": 90.0, "top": 180.0, "left": 270.0}[start]
    cx, cy = centre
    offset = {"bottom": (0.0, -h / 2), "right": (w / 2, 0.0), "top": (0.0, h / 2), "left": (-w / 2, 0.0)}[start]
    moves: list[tuple[str, float, float]] = [
        ("line", first / 2 - r, 0),
        ("arc", r, 90),
        ("line", second - 2 * r, 0),
        ("arc", r, 90),
        ("line", first - 2 * r, 0),
        ("arc", r, 90),
        ("line", second - 2 * r, 0),
        ("arc", r, 90),
        ("line", first / 2 - r, 0),
    ]
    return closed_turtle((cx + offset[0], cy + offset[1]), heading, moves)


def notched_loop(
    start: Sequence[float],
    stretch: float,
    *,
    side: float,
    height: float,
    corner: float,
    notch_depth: float,
    notch_radius: float,
    ccw: bool = True,
) -> Route:
    """Closed loop with a notch: a short straight ``stretch`` between two tight turns, driven eastwards.

    The route starts at the middle of the stretch (``start``), heading east. Counter-clockwise, the loop lies
    north of the stretch: the vehicle comes down into the notch from the loop's bottom side, turns left onto
    the stretch and left again back up; clockwise it is the mirror image (loop to the south, notch pointing
    up, right turns). The loop's main part is a rounded rectangle whose bottom (top) side carries the notch.

    Args:
        start: (x, y) middle of the stretch.
        stretch: length of the stretch (may be 0).
        side: length of the main side on each side of the notch (m).
        height: length of the straight sides of the main loop (m).
        corner: corner radius of the main loop (m).
        notch_depth: straight part of the notch's vertical legs (m).
        notch_radius: radius of the notch's four quarter turns (m).
        ccw: counter-clockwise (loop north) or clockwise (loop south).

    """
    sign = 1.0 if ccw else -1.0
    width = stretch + 4.0 * notch_radius + 2.0 * side
    moves: list[tuple[str, float, float]] = [
        ("line", stretch / 2, 0),
        ("arc", notch_radius, 90 * sign),
        ("line", notch_depth, 0),
        ("arc", notch_radius, -90 * sign),
        ("line", side, 0),
        ("arc", corner, 90 * sign),
        ("line", height, 0),
        ("arc", corner, 90 * sign),
        ("line", width, 0),
        ("arc", corner, 90 * sign),
        ("line", height, 0),
        ("arc", corner, 90 * sign),
        ("line", side, 0),
        ("arc", notch_radius, -90 * sign),
        ("line", notch_depth, 0),
        ("arc", notch_radius, 90 * sign),
        ("line", stretch / 2, 0),
    ]
    return closed_turtle(start, 0.0, moves)


def segment(route: Route, s0: float, s1: float) -> Route:
    """Return the open piece of ``route`` from arc length ``s0`` to ``s1`` (``s1 > s0``; laps allowed)."""
    n = max(2, math.ceil((s1 - s0) / VERTEX_SPACING_M) + 1)
    return from_points(route.position(np.linspace(s0, s1, n)), closed=False)


def concat(pieces: Sequence[Route]) -> Route:
    """Join open routes end to start (each piece must start where the previous one ended, to 1 cm)."""
    pts = [pieces[0].xy]
    for prev, nxt in itertools.pairwise(pieces):
        gap = float(np.linalg.norm(prev.xy[-1] - nxt.xy[0]))
        if gap > 0.01:
            msg = f"route pieces do not join (gap {gap:.3f} m)"
            raise ValueError(msg)
        pts.append(nxt.xy[1:])
    return from_points(np.vstack(pts), closed=False)

"""A tiny deterministic world for merge tests: a closed route whose camera view depends on the arc position.

The route is a circle or a stadium (two straights joined by half circles) of a given
perimeter, optionally with a depth profile z(s). The camera view at arc length s is a
window of a smooth random texture strip (different places differ, one place looks the
same on every visit), and the odometry between frames is the exact body-frame motion
between the true poses. Two sessions that start at different arc positions see the same
views where their paths overlap, with frames rotated by the angle between their starts.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from core import Motion

Frame = tuple[np.ndarray, Motion, float]


class LoopWorld:
    """Closed route, texture strip and frame generator.

    Args:
        perimeter: route length (m).
        px_per_m: texture columns per metre of route.
        height, width: camera image size (px).
        seed: texture seed.
        straight: length of each straight (m); 0 gives a circle.
        depth: amplitude (m) of a depth profile z(s) = depth·sin(2πs/perimeter) (4-DoF tests).
        alias: optional (source_m, target_m, length_m): the texture over [target, target + length)
            is a copy of the texture over [source, source + length) (two look-alike places).
    """

    def __init__(
        self,
        perimeter: float = 40.0,
        px_per_m: float = 8.0,
        height: int = 24,
        width: int = 64,
        seed: int = 3,
        straight: float = 0.0,
        depth: float = 0.0,
        alias: tuple[float, float, float] | None = None,
    ) -> None:
        rng = np.random.default_rng(seed)
        self.perimeter = perimeter
        self.px_per_m = px_per_m
        self.width = width
        self.columns = round(perimeter * px_per_m)
        base = rng.random((height, self.columns))
        kernel = np.ones(5) / 5.0
        smooth = np.stack([np.convolve(np.concatenate([r[-2:], r, r[:2]]), kernel, "valid") for r in base])
        # places also differ in brightness, as real scenes do (the template-mean prefilter sees it)
        phase = np.arange(self.columns) / self.columns * 2.0 * math.pi
        brightness = 1.0 + 0.35 * np.sin(phase + rng.uniform(0, 2 * math.pi)) * np.sin(3 * phase)
        contrast = (smooth - smooth.mean()) / smooth.std()  # unit spread: distinct places differ clearly
        texture = np.clip(brightness[None, :] * (128.0 + 55.0 * contrast), 0, 255)
        if alias is not None:
            src, dst, length = (round(v * px_per_m) for v in alias)
            cols = (np.arange(length) + src) % self.columns
            texture[:, (np.arange(length) + dst) % self.columns] = texture[:, cols]
        self.texture = texture.astype(np.uint8)
        self.straight = straight
        self.radius = (perimeter - 2.0 * straight) / (2.0 * math.pi)
        self.depth = depth

    def view(self, s: float) -> np.ndarray:
        """Return the camera image at arc length ``s`` (m)."""
        start = round(s * self.px_per_m) % self.columns
        idx = (start + np.arange(self.width)) % self.columns
        return self.texture[:, idx]

    def pose(self, s: float) -> np.ndarray:
        """Return the true pose (x, y, z, yaw) at arc length ``s``: straight, half circle, straight, half circle."""
        s = s % self.perimeter
        a, r = self.straight, self.radius
        half = math.pi * r
        z = self.depth * math.sin(2.0 * math.pi * s / self.perimeter)
        if s < a:
            return np.array([s, 0.0, z, 0.0])
        s -= a
        if s < half:
            t = s / r
            return np.array([a + r * math.sin(t), r * (1.0 - math.cos(t)), z, t])
        s -= half
        if s < a:
            return np.array([a - s, 2.0 * r, z, math.pi])
        s -= a
        t = s / r
        return np.array([-r * math.sin(t), r * (1.0 + math.cos(t)), z, math.pi + t])

    def drive(self, start: float, distance: float, step: float = 0.5, dt: float = 0.5, t0: float = 0.0) -> list[Frame]:
        """Return frames from arc length ``start`` over ``distance`` metres, ``step`` metres apart."""
        n = round(distance / step) + 1
        frames: list[Frame] = []
        previous = self.pose(start)
        for i in range(n):
            s = start + i * step
            pose = self.pose(s)
            if i == 0:
                motion = Motion(0.0, 0.0, 0.0, 0.0, 0.0)
            else:
                c, sn = math.cos(previous[3]), math.sin(previous[3])
                dx, dy = pose[0] - previous[0], pose[1] - previous[1]
                dyaw = math.remainder(pose[3] - previous[3], 2.0 * math.pi)
                motion = Motion(c * dx + sn * dy, -sn * dx + c * dy, pose[2] - previous[2], dyaw, dt)
            frames.append((self.view(s), motion, t0 + i * dt))
            previous = pose
        return frames

    def arc(self, start: float, distance: float, step: float = 0.5) -> np.ndarray:
        """Return the arc positions (m, modulo the perimeter) of :meth:`drive`'s frames."""
        n = round(distance / step) + 1
        return (start + step * np.arange(n)) % self.perimeter


def true_poses(world: LoopWorld, arcs: Sequence[float]) -> np.ndarray:
    """Return the true poses (N, 4) at the given arc positions."""
    return np.stack([world.pose(float(s)) for s in arcs])

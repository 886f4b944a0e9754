"""Tiny deterministic test worlds shared by the engine and store tests: a 'corridor' with exact revisits, a panorama."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from core.motion import Motion


class StripWorld:
    """A closed route whose camera view at arc length s is a window of a smooth random texture strip.

    Views of one place are identical on every lap, different places differ, so a loop closes exactly
    where the route repeats.
    """

    def __init__(
        self, perimeter_m: float = 40.0, px_per_m: float = 8.0, height: int = 24, width: int = 64, seed: int = 3
    ) -> None:
        rng = np.random.default_rng(seed)
        self.columns = int(perimeter_m * px_per_m)
        base = rng.random((height, self.columns))
        # smooth along the route so small pose changes give similar views
        kernel = np.ones(5) / 5.0
        smooth = np.stack([np.convolve(np.concatenate([r[-2:], r, r[:2]]), kernel, "valid") for r in base])
        self.texture = (40 + 180 * smooth).astype(np.uint8)
        self.perimeter = perimeter_m
        self.px_per_m = px_per_m
        self.width = width

    def view(self, s: float) -> np.ndarray:
        """Return the camera image at arc length ``s`` (m)."""
        start = round(s * self.px_per_m) % self.columns
        return self.texture[:, (start + np.arange(self.width)) % self.columns]

    def drive(
        self, laps: float, speed: float = 1.0, dt: float = 0.5, yaw_bias: float = 0.0
    ) -> Iterator[tuple[np.ndarray, Motion, float]]:
        """Yield (image, motion, stamp) around a circle of the perimeter (odometry yaw rate biased by ``yaw_bias``)."""
        radius = self.perimeter / (2 * math.pi)
        turn = speed * dt / radius + yaw_bias * dt
        for i in range(int(laps * self.perimeter / (speed * dt))):
            motion = Motion(0.0, 0.0, 0.0, 0.0, 0.0) if i == 0 else Motion(speed * dt, 0.0, 0.0, turn, dt)
            yield self.view(i * speed * dt), motion, i * dt


def smooth_panorama() -> np.ndarray:
    """A 64 × 256 random image box-filtered over 16 columns: smooth, so a match's error is a bowl around its shift."""
    rng = np.random.default_rng(4)
    image = np.clip(rng.normal(128.0, 40.0, (64, 256 + 16)), 0, 255)
    image = np.cumsum(np.cumsum(image, axis=1), axis=0)
    image = (image[:, 16:] - image[:, :-16])[:, :256]
    return (255.0 * (image - image.min()) / np.ptp(image)).astype(np.uint8)

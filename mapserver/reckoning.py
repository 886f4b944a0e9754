"""Dead reckoning of a session's raw odometry: the positions evaluation compares with ground truth."""

from __future__ import annotations

import math

import numpy as np

from core.motion import Motion


class DeadReckoning:
    """Integrates the frames' motions into raw odometry positions (for evaluation against ground truth)."""

    def __init__(self, initial_yaw: float) -> None:
        self.pose = np.array([0.0, 0.0, 0.0, initial_yaw])
        self.rows: list[tuple[float, float, float, float]] = []

    def add(self, stamp: float, motion: Motion) -> None:
        """Compose one body-frame motion and record the position at ``stamp``."""
        x, y, z, yaw = self.pose
        c, s = math.cos(yaw), math.sin(yaw)
        self.pose = np.array(
            [x + c * motion.dx - s * motion.dy, y + s * motion.dx + c * motion.dy, z + motion.dz, yaw + motion.dyaw]
        )
        self.rows.append((stamp, float(self.pose[0]), float(self.pose[1]), float(self.pose[2])))

    def array(self) -> np.ndarray:
        """Return the (N, 4) ``[stamp, x, y, z]`` rows."""
        return np.asarray(self.rows, dtype=np.float64).reshape(-1, 4)

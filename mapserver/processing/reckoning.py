"""Dead reckoning of a session's raw odometry: the positions evaluation compares with ground truth."""

from __future__ import annotations

import numpy as np

from core.motion import Motion
from core.se3 import compose_step


class DeadReckoning:
    """Integrates the frames' motions into raw odometry positions (for evaluation against ground truth)."""

    def __init__(self, initial_yaw: float) -> None:
        self.pose = np.array([0.0, 0.0, 0.0, initial_yaw])
        self.rows: list[tuple[float, float, float, float]] = []

    def add(self, stamp: float, motion: Motion) -> None:
        """Compose one body-frame motion (heading summed, not wrapped) and record the position at ``stamp``."""
        self.pose = np.array(compose_step(self.pose.tolist(), (motion.dx, motion.dy, motion.dz, motion.dyaw)))
        self.rows.append((stamp, float(self.pose[0]), float(self.pose[1]), float(self.pose[2])))

    def array(self) -> np.ndarray:
        """Return the (N, 4) ``[stamp, x, y, z]`` rows."""
        return np.asarray(self.rows, dtype=np.float64).reshape(-1, 4)

"""Odometry increments fed to the engine, one per camera frame."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Motion:
    """Rigid 4-DoF motion of the vehicle between two consecutive camera frames.

    The displacement is expressed in the body frame of the *previous* frame
    (x forward, y left, z up; yaw counter-clockwise about z), which is what
    integrating ``nav_msgs/Odometry`` twist over the interval gives.

    Attributes:
        dx: forward displacement in metres.
        dy: leftward displacement in metres.
        dz: upward displacement in metres.
        dyaw: heading change in radians.
        dt: elapsed time in seconds (> 0 except for the first frame).
    """

    dx: float
    dy: float
    dz: float
    dyaw: float
    dt: float

    @property
    def forward_speed(self) -> float:
        """Return the forward speed ``dx/dt`` in m/s (0 when ``dt`` is 0)."""
        return self.dx / self.dt if self.dt > 0 else 0.0

    @property
    def yaw_rate(self) -> float:
        """Return the yaw rate ``dyaw/dt`` in rad/s (0 when ``dt`` is 0)."""
        return self.dyaw / self.dt if self.dt > 0 else 0.0

    @property
    def vertical_speed(self) -> float:
        """Return the vertical speed ``dz/dt`` in m/s (0 when ``dt`` is 0)."""
        return self.dz / self.dt if self.dt > 0 else 0.0


ZERO_MOTION = Motion(0.0, 0.0, 0.0, 0.0, 0.0)

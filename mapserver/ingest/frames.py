"""The unit a mission log is read into: one camera frame plus the motion before it; what reading dropped."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from core.motion import Motion


@dataclass(frozen=True, slots=True)
class Frame:
    """One camera frame, in stamp order, with the odometry integrated up to its stamp.

    Attributes:
        stamp_ns: ROS stamp of the image, nanoseconds.
        image: uint8 pixels, shape (H, W) for grey or (H, W, 3) RGB.
        motion: motion since the previous frame from the log's odometry, or None
            when the log has no odometry (the engine then uses visual odometry).
        sonar: the newest image of the sonar topic at or before the stamp (``--topics sonar=/t``), None
            without one (no sonar topic, or none received yet).
    """

    stamp_ns: int
    image: npt.NDArray[np.uint8]
    motion: Motion | None
    sonar: npt.NDArray[np.uint8] | None = None


@dataclass(frozen=True, slots=True)
class PoseSample:
    """One ground-truth (or odometry) pose: stamp and SE(3) pose as position + quaternion."""

    stamp_ns: int
    x: float
    y: float
    z: float
    qx: float
    qy: float
    qz: float
    qw: float


@dataclass(slots=True)
class IngestReport:
    """What reading a log dropped on its way to the engine, counted by reason (:class:`OdometryCheck`).

    Attributes:
        odometry_messages: odometry messages read.
        frames: frames whose motion was worked out from the odometry.
        dropped_messages: odometry messages dropped, by reason (the motion across them comes from their
            neighbours: the previous twist held, or the poses on either side interpolated).
        dropped_motions: frames whose motion was dropped (zero displacement over the frame's dt), by reason.
    """

    odometry_messages: int = 0
    frames: int = 0
    dropped_messages: dict[str, int] = field(default_factory=dict)
    dropped_motions: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """Return ``{"odometry_messages", "frame_motions", "reasons"}``: the counts dropped and why."""
        reasons = {f"odometry message: {k}": v for k, v in self.dropped_messages.items()}
        reasons.update({f"frame motion: {k}": v for k, v in self.dropped_motions.items()})
        return {
            "odometry_messages": sum(self.dropped_messages.values()),
            "frame_motions": sum(self.dropped_motions.values()),
            "reasons": reasons,
        }

    def warning(self) -> str | None:
        """Return one line saying what was dropped and why, None when nothing was."""
        parts = []
        if self.dropped_messages:
            parts.append(f"{sum(self.dropped_messages.values())} of {self.odometry_messages} odometry messages "
                         f"({_reasons(self.dropped_messages)})")  # fmt: skip
        if self.dropped_motions:
            parts.append(f"the motion of {sum(self.dropped_motions.values())} of {self.frames} frames "
                         f"({_reasons(self.dropped_motions)})")  # fmt: skip
        return f"dropped {' and '.join(parts)}" if parts else None


def _reasons(counts: dict[str, int]) -> str:
    """Return ``reason: count, ...``."""
    return ", ".join(f"{reason}: {count}" for reason, count in counts.items())

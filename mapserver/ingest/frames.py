"""The unit a mission log is read into: one camera frame plus the motion before it."""

from __future__ import annotations

from dataclasses import dataclass

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

"""Visual odometry from scanline intensity profiles (OpenRatSLAM ``VisualOdometry``; anchors §1.1).

Each frame's crop windows (``vtrans_image_*`` and ``vrot_image_*``) are reduced to
column-intensity profiles (mean of each column / 255). The current profile is
compared with the previous one at every column shift s with |s| < 40 pixels
(OpenRatSLAM's fixed search range, narrowed for profiles shorter than that), by
the mean absolute difference over the overlap. The best shift of the rotation
profile gives the yaw rate ``s · camera_fov_deg/image_width · rate`` (degrees per
pixel of the whole image, as OpenRatSLAM); the smallest difference of the
translation profile gives the speed ``min_diff · vtrans_scaling`` capped at
``vtrans_max``.

Deliberate deviations from OpenRatSLAM: ``rate`` is ``1/dt`` when the frame
interval is known, so the estimate does not depend on the playback rate
(OpenRatSLAM uses ``camera_hz``, the fallback here, and always with
``openratslam_compat``); the first frame gives zero motion (OpenRatSLAM compares it
with an all-zero profile).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, cast

import numpy as np

from core.arrays import FloatArray, UInt8Array
from core.config import Departure
from core.localview import crop, greyscale

if TYPE_CHECKING:
    from core.config import Params


def column_profile(grey: FloatArray, x_min: int, x_max: int, y_min: int, y_max: int) -> FloatArray:
    """Return the column means (/255) of the cropped window."""
    return cast(FloatArray, crop(grey, x_min, x_max, y_min, y_max).mean(axis=0) / 255.0)


MAX_SHIFT = 40  #: OpenRatSLAM ``visual_odo``: offsets 0..39 pixels each way


def best_shift(current: FloatArray, previous: FloatArray, max_shift: int = MAX_SHIFT) -> tuple[int, float]:
    """Return (shift, mean abs difference) minimising the mean |current[k+s] − previous[k]| over the overlap.

    Shifts −s compare ``current[k]`` with ``previous[k+s]``. Positive shifts mean the
    scene moved towards higher columns. Shifts are tried in OpenRatSLAM's order —
    0, −1, …, −(n−1), then 1, …, n−1 with n = min(``max_shift``, width) — and a
    later one wins only when strictly better.
    """
    width = current.shape[0]
    best = (0, math.inf)
    limit = min(max_shift, width)
    for offset in range(limit):  # current[k] against previous[k + offset]: shift −offset
        diff = float(np.abs(current[: width - offset] - previous[offset:]).mean())
        if diff < best[1]:
            best = (-offset, diff)
    for offset in range(limit):  # current[k + offset] against previous[k]: shift +offset
        diff = float(np.abs(current[offset:] - previous[: width - offset]).mean())
        if diff < best[1]:
            best = (offset, diff)
    return best


class VisualOdometry:
    """Estimates forward speed and yaw rate from consecutive camera frames."""

    def __init__(self, params: Params) -> None:
        self.params = params
        self.prev_vtrans = np.zeros(0)
        self.prev_vrot = np.zeros(0)

    def process(self, image: UInt8Array, dt: float) -> tuple[float, float]:
        """Return (vtrans m/s, vrot rad/s) for ``image``; (0, 0) on the first frame."""
        p = self.params
        grey = greyscale(image)
        vtrans_profile = column_profile(
            grey, p.vtrans_image_x_min, p.vtrans_image_x_max, p.vtrans_image_y_min, p.vtrans_image_y_max
        )
        vrot_profile = column_profile(
            grey, p.vrot_image_x_min, p.vrot_image_x_max, p.vrot_image_y_min, p.vrot_image_y_max
        )
        vtrans = vrot = 0.0
        if self.prev_vtrans.shape == vtrans_profile.shape and self.prev_vrot.shape == vrot_profile.shape:
            rate = p.camera_hz if dt <= 0 or p.follows_openratslam(Departure.VO_INTERVAL) else 1.0 / dt
            shift, _ = best_shift(vrot_profile, self.prev_vrot)
            vrot = shift * math.radians(p.camera_fov_deg) / grey.shape[1] * rate
            _, diff = best_shift(vtrans_profile, self.prev_vtrans)
            vtrans = min(diff * p.vtrans_scaling, p.vtrans_max)
        self.prev_vtrans = vtrans_profile
        self.prev_vrot = vrot_profile
        return vtrans, vrot

    def snapshot(self) -> dict[str, FloatArray]:
        """Return the previous profiles (keys ``vo_*``)."""
        return {"vo_prev_vtrans": self.prev_vtrans.copy(), "vo_prev_vrot": self.prev_vrot.copy()}

    @classmethod
    def restore(cls, params: Params, state: Mapping[str, np.ndarray]) -> VisualOdometry:
        """Rebuild from :meth:`snapshot` arrays."""
        vo = cls(params)
        vo.prev_vtrans = np.asarray(state["vo_prev_vtrans"], dtype=np.float64).copy()
        vo.prev_vrot = np.asarray(state["vo_prev_vrot"], dtype=np.float64).copy()
        return vo

"""What a log says about its camera: the image size, and the field of view when a ``CameraInfo`` topic gives it.

* **Image size**: the first frame of the image topic, decoded as ``process`` decodes it (width × height in
  pixels, after decompression).
* **Field of view**: horizontal, from the first message of a ``sensor_msgs/CameraInfo`` topic — the one in the
  image topic's namespace (``/cam/image_raw`` → ``/cam/camera_info``), else the only one — as
  ``2·atan(width / (2·fx))`` (pinhole model; ``fx`` is the intrinsic matrix's first entry, ``K[0]``). A
  ``CameraInfo`` with no focal length (``fx`` ≤ 0, uncalibrated), no width or a message that does not decode
  gives none. Logs without such a topic (the simulator's, many recorded ones) leave the field of view to the user.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from mapserver.errors import IngestError
from mapserver.ingest.decode import decode_image

if TYPE_CHECKING:
    from mapserver.ingest.reader import MissionLog

CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"


@dataclass(frozen=True, slots=True)
class CameraGeometry:
    """The camera as the log shows it: image size in pixels, field of view (degrees) and the topic that gave it."""

    width: int
    height: int
    fov_deg: float | None = None
    fov_topic: str | None = None


def pinhole_fov_deg(width: float, fx: float) -> float | None:
    """Return the horizontal field of view ``2·atan(width / (2·fx))`` in degrees (None unless both are > 0)."""
    if not (width > 0 and fx > 0 and math.isfinite(width) and math.isfinite(fx)):
        return None
    return math.degrees(2.0 * math.atan(width / (2.0 * fx)))


def camera_info_topic(topics: list[tuple[str, str]], image_topic: str) -> str | None:
    """Return the ``CameraInfo`` topic that belongs to ``image_topic`` among (name, type) pairs, or None.

    The one sharing the image topic's namespace (its name up to the last ``/``) wins; otherwise the only
    ``CameraInfo`` topic of the log; with several and none in that namespace, none.
    """
    infos = sorted(name for name, msgtype in topics if msgtype == CAMERA_INFO_TYPE)
    namespace = image_topic.rsplit("/", 1)[0]
    near = [name for name in infos if name.rsplit("/", 1)[0] == namespace]
    if near:
        return near[0]
    return infos[0] if len(infos) == 1 else None


def _fov_from_message(msg: Any) -> float | None:
    matrix = getattr(msg, "k", None)
    if matrix is None:
        matrix = getattr(msg, "K", None)
    if matrix is None or len(matrix) < 1:
        return None
    return pinhole_fov_deg(float(getattr(msg, "width", 0)), float(matrix[0]))


def read_camera(log: MissionLog) -> CameraGeometry:
    """Return the log's camera geometry (module docstring): first frame's size, ``CameraInfo``'s field of view.

    Raises:
        IngestError: the first image does not decode.
    """
    first = log.first_image()
    image = decode_image(first, log.mapping.image)
    height, width = int(image.shape[0]), int(image.shape[1])
    topic = camera_info_topic([(t.name, t.msgtype) for t in log.topics if t.count], log.mapping.image)
    if topic is None:
        return CameraGeometry(width, height)
    try:
        fov = _fov_from_message(log.first_message(topic))
    except IngestError:  # a damaged CameraInfo leaves the field of view to the user; the log stays usable
        fov = None
    return CameraGeometry(width, height, fov, topic if fov is not None else None)

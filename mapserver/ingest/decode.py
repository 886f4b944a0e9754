"""Image messages to pixels: ``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` → uint8 RGB or grey.

Raw ``Image`` encodings: ``mono8`` (alias ``8UC1``), ``mono16`` (alias ``16UC1``; scaled to 8 bit as
``value >> 8``, byte order from ``is_bigendian``), ``rgb8``, ``bgr8``, ``rgba8`` and ``bgra8`` (alpha
dropped). Row padding given by ``step`` is honoured. ``CompressedImage`` with a JPEG or PNG payload is
decoded with OpenCV (colour returned as RGB, 16-bit PNG scaled like ``mono16``). Anything else raises
:class:`~mapserver.errors.IngestError`.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from mapserver.errors import IngestError

RAW_ENCODINGS = frozenset({"mono8", "8uc1", "mono16", "16uc1", "rgb8", "bgr8", "rgba8", "bgra8"})
_CHANNELS = {"mono8": 1, "8uc1": 1, "mono16": 2, "16uc1": 2, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}
_COMPRESSED_OK = ("jpeg", "jpg", "png")


def is_compressed(msg: Any) -> bool:
    """Return True for a ``CompressedImage`` (it has ``format`` and no ``encoding``)."""
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


def image_format(msg: Any) -> str:
    """Return the encoding of an ``Image`` or the format of a ``CompressedImage`` (as stored)."""
    return str(msg.format if is_compressed(msg) else msg.encoding)


def check_supported(msg: Any, topic: str = "") -> None:
    """Raise IngestError when the message's encoding is not one :func:`decode_image` handles.

    Args:
        msg: a deserialised ``Image`` or ``CompressedImage``.
        topic: topic name for the error message.

    Raises:
        IngestError: unsupported encoding or compressed format.

    """
    if is_compressed(msg):
        fmt = str(msg.format).lower()
        if "compresseddepth" in fmt or (fmt.strip() and not any(k in fmt for k in _COMPRESSED_OK)):
            msg_ = f"unsupported compressed image format {msg.format!r} on {topic}"
            raise IngestError(msg_)
        return
    if str(msg.encoding).lower() not in RAW_ENCODINGS:
        msg_ = f"unsupported image encoding {msg.encoding!r} on {topic}"
        raise IngestError(msg_)


def decode_image(msg: Any, topic: str = "") -> npt.NDArray[np.uint8]:
    """Decode an image message into uint8 pixels.

    Args:
        msg: a deserialised ``sensor_msgs/msg/Image`` or ``sensor_msgs/msg/CompressedImage``.
        topic: topic name for error messages.

    Returns:
        A C-contiguous uint8 array, (H, W) for grey or (H, W, 3) RGB.

    Raises:
        IngestError: unsupported encoding, or data inconsistent with the declared size.

    """
    check_supported(msg, topic)
    if is_compressed(msg):
        return _decode_compressed(msg, topic)
    return _decode_raw(msg, topic)


def _decode_raw(msg: Any, topic: str) -> npt.NDArray[np.uint8]:
    encoding = str(msg.encoding).lower()
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    channels = _CHANNELS[encoding]
    row_bytes = width * channels
    data = _as_uint8(msg.data)
    if step < row_bytes or data.size < height * step or height <= 0 or width <= 0:
        msg_ = (
            f"corrupt image on {topic}: {width}x{height} {msg.encoding} step {step} "
            f"with {data.size} bytes of data"
        )
        raise IngestError(msg_)
    rows = data[: height * step].reshape(height, step)[:, :row_bytes]
    if encoding in ("mono8", "8uc1"):
        return np.ascontiguousarray(rows)
    if encoding in ("mono16", "16uc1"):
        dtype = np.dtype(">u2") if msg.is_bigendian else np.dtype("<u2")
        values = np.ascontiguousarray(rows).view(dtype).reshape(height, width)
        return (values >> 8).astype(np.uint8)
    pixels = rows.reshape(height, width, channels)
    if encoding == "rgb8":
        return np.ascontiguousarray(pixels)
    if encoding == "rgba8":
        return np.ascontiguousarray(pixels[:, :, :3])
    # bgr8, bgra8
    return np.ascontiguousarray(pixels[:, :, 2::-1])


def _decode_compressed(msg: Any, topic: str) -> npt.NDArray[np.uint8]:
    buffer = _as_uint8(msg.data)
    image = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED) if buffer.size else None
    if image is None:
        msg_ = f"cannot decode compressed image ({msg.format!r}, {buffer.size} bytes) on {topic}"
        raise IngestError(msg_)
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        msg_ = f"unsupported compressed image depth {image.dtype} on {topic}"
        raise IngestError(msg_)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    elif image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    elif image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return np.ascontiguousarray(image)


def _as_uint8(data: Any) -> npt.NDArray[np.uint8]:
    """Return message data (numpy array, bytes or a list of ints) as a flat uint8 array without copying."""
    if isinstance(data, np.ndarray):
        return (
            data.reshape(-1).view(np.uint8) if data.dtype.itemsize == 1 else data.astype(np.uint8).reshape(-1)
        )
    if isinstance(data, bytes | bytearray | memoryview):
        return np.frombuffer(data, dtype=np.uint8)
    return np.asarray(data, dtype=np.uint8).reshape(-1)

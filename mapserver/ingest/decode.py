"""Image messages to pixels: ``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` → uint8 RGB or grey.

Raw ``Image`` encodings: ``mono8`` (alias ``8UC1``), ``mono16`` (alias ``16UC1``; scaled to 8 bit as
``value >> 8``, byte order from ``is_bigendian``), ``rgb8``, ``bgr8``, ``rgba8`` and ``bgra8`` (alpha
dropped). Row padding given by ``step`` is honoured. ``CompressedImage`` with a JPEG or PNG payload is
decoded with OpenCV (colour returned as RGB, 16-bit PNG scaled like ``mono16``). Anything else raises
:class:`~mapserver.errors.IngestError`.

Pixel limit: a frame may have at most ``max_pixels`` pixels (width × height), checked before anything is
decoded: a raw ``Image``'s size from its ``width`` and ``height`` fields, a PNG's from its IHDR chunk, a
JPEG's from its first SOF marker (a payload that is neither, or whose header does not parse, is refused).
A larger frame raises :class:`~mapserver.errors.LimitError` (``max_image_pixels``). The limit is the
``max_pixels`` argument, else the process's setting (:func:`set_max_image_pixels`: ``process
--max-image-pixels``, ``serve --max-image-pixels``), else ``$MAPSERVER_MAX_IMAGE_PIXELS``, else
:data:`DEFAULT_MAX_IMAGE_PIXELS`.
"""

from __future__ import annotations

import os
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from core.config import ConfigError
from mapserver.errors import IngestError, LimitError

DEFAULT_MAX_IMAGE_PIXELS = 1 << 25  # 33.5 Mpx: an 8K (7680×4320) frame fits
PIXELS_ENV = "MAPSERVER_MAX_IMAGE_PIXELS"
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}  # start-of-frame markers (not DHT, JPG, DAC)
_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xD9)})  # TEM, RSTn, SOI: no length field
_process_max_pixels: int | None = None
RAW_ENCODINGS = frozenset({"mono8", "8uc1", "mono16", "16uc1", "rgb8", "bgr8", "rgba8", "bgra8"})
_CHANNELS = {"mono8": 1, "8uc1": 1, "mono16": 2, "16uc1": 2, "rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}
_COMPRESSED_OK = ("jpeg", "jpg", "png")


def is_compressed(msg: Any) -> bool:
    """Return True for a ``CompressedImage`` (it has ``format`` and no ``encoding``)."""
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


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


def max_image_pixels() -> int:
    """Return the process's pixel limit (see the module docstring)."""
    if _process_max_pixels is not None:
        return _process_max_pixels
    text = os.environ.get(PIXELS_ENV)
    if text is None:
        return DEFAULT_MAX_IMAGE_PIXELS
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        msg = f"{PIXELS_ENV} must be a positive integer, got {text!r}"
        raise ConfigError(msg)
    return value


def set_max_image_pixels(value: int | None) -> int | None:
    """Set the process's pixel limit (None: the environment's or the default); return the previous setting."""
    global _process_max_pixels  # one setting per process: every reader thread reads it
    if value is not None and value < 1:
        msg = f"the image pixel limit must be at least 1, got {value!r}"
        raise ConfigError(msg)
    previous, _process_max_pixels = _process_max_pixels, value
    return previous


def decode_image(msg: Any, topic: str = "", *, max_pixels: int | None = None) -> npt.NDArray[np.uint8]:
    """Decode an image message into uint8 pixels.

    Args:
        msg: a deserialised ``sensor_msgs/msg/Image`` or ``sensor_msgs/msg/CompressedImage``.
        topic: topic name for error messages.
        max_pixels: the pixel limit (None: the process's, see the module docstring).

    Returns:
        A C-contiguous uint8 array, (H, W) for grey or (H, W, 3) RGB.

    Raises:
        LimitError: the image has more than ``max_pixels`` pixels (nothing decoded).
        IngestError: unsupported encoding, unparsable header, or data inconsistent with the declared size.

    """
    check_supported(msg, topic)
    limit = max_image_pixels() if max_pixels is None else max_pixels
    if is_compressed(msg):
        return _decode_compressed(msg, topic, limit)
    return _decode_raw(msg, topic, limit)


def _check_pixels(width: int, height: int, limit: int, topic: str) -> None:
    if width * height > limit:
        msg = (
            f"image on {topic} is {width}x{height} = {width * height} pixels, more than the limit "
            f"max_image_pixels = {limit}"
        )
        raise LimitError(msg, limit="max_image_pixels")


def compressed_size(data: bytes | npt.NDArray[np.uint8]) -> tuple[int, int] | None:
    """Return ``(width, height)`` from a PNG's IHDR or a JPEG's first SOF marker, None when neither parses."""
    head = bytes(data[:33])
    if head.startswith(_PNG_SIGNATURE):
        if len(head) < 24 or head[12:16] != b"IHDR":
            return None
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if not head.startswith(b"\xff\xd8"):
        return None
    view = memoryview(data if isinstance(data, bytes) else np.ascontiguousarray(data)).cast("B")  # type: ignore[arg-type]  # numpy's stubs: ndarray is a buffer
    pos = 2
    while pos + 4 <= len(view):
        if view[pos] != 0xFF:
            return None
        marker = view[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in _JPEG_STANDALONE:
            pos += 2
            continue
        if marker in (0xD9, 0xDA):  # EOI or start of scan before any frame header
            return None
        length = int.from_bytes(view[pos + 2 : pos + 4], "big")
        if marker in _JPEG_SOF:
            if length < 7 or pos + 9 > len(view):
                return None
            return int.from_bytes(view[pos + 7 : pos + 9], "big"), int.from_bytes(view[pos + 5 : pos + 7], "big")
        if length < 2:
            return None
        pos += 2 + length
    return None


def _decode_raw(msg: Any, topic: str, limit: int) -> npt.NDArray[np.uint8]:
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
    _check_pixels(width, height, limit, topic)
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


def _decode_compressed(msg: Any, topic: str, limit: int) -> npt.NDArray[np.uint8]:
    buffer = _as_uint8(msg.data)
    size = compressed_size(buffer)
    if size is None or size[0] <= 0 or size[1] <= 0:
        msg_ = f"cannot decode compressed image ({msg.format!r}, {buffer.size} bytes) on {topic}: no JPEG or PNG header"
        raise IngestError(msg_)
    _check_pixels(size[0], size[1], limit, topic)
    image = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED)
    if image is None:
        msg_ = f"cannot decode compressed image ({msg.format!r}, {buffer.size} bytes) on {topic}"
        raise IngestError(msg_)
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)  # type: ignore[operator]  # cv2's stubs: a uint16 image shifts
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

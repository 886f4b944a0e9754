from __future__ import annotations

import cv2
import numpy as np
import pytest

from mapserver.errors import IngestError
from mapserver.ingest.decode import decode_image
from tests.mapserver.ingest.conftest import ROS1, ROS2, header, test_image

IMAGE = ROS2.types["sensor_msgs/msg/Image"]
COMPRESSED = ROS2.types["sensor_msgs/msg/CompressedImage"]


def raw(pixels: np.ndarray, encoding: str, step: int, big: int = 0, h: int = 5, w: int = 7) -> object:
    return IMAGE(
        header=header(ROS2, 1), height=h, width=w, encoding=encoding, is_bigendian=big, step=step, data=pixels
    )


def padded(rows: np.ndarray, pad: int) -> np.ndarray:
    """Append ``pad`` garbage bytes to each row of a (H, row_bytes) array and flatten."""
    garbage = np.full((rows.shape[0], pad), 0xAB, dtype=np.uint8)
    return np.concatenate([rows, garbage], axis=1).reshape(-1)


def test_mono8_with_step_padding() -> None:
    grey = test_image(0, colour=False, shape=(5, 7))
    out = decode_image(raw(padded(grey, 3), "mono8", step=10))
    assert out.dtype == np.uint8 and out.shape == (5, 7) and out.flags.c_contiguous
    np.testing.assert_array_equal(out, grey)


@pytest.mark.parametrize("big", [0, 1])
def test_mono16_scaled_and_endianness(big: int) -> None:
    values = np.arange(35, dtype=np.uint16).reshape(5, 7) * 1871  # spans most of 0..65535
    data = values.astype(">u2" if big else "<u2").view(np.uint8).reshape(5, 14)
    out = decode_image(raw(padded(data, 2), "mono16", step=16, big=big))
    np.testing.assert_array_equal(out, (values >> 8).astype(np.uint8))


@pytest.mark.parametrize(
    ("encoding", "convert"),
    [
        ("rgb8", lambda rgb: rgb),
        ("bgr8", lambda rgb: rgb[:, :, ::-1]),
        ("rgba8", lambda rgb: np.concatenate([rgb, np.full((5, 7, 1), 9, np.uint8)], axis=2)),
        ("bgra8", lambda rgb: np.concatenate([rgb[:, :, ::-1], np.full((5, 7, 1), 9, np.uint8)], axis=2)),
    ],
)
def test_colour_encodings_to_rgb(encoding: str, convert: object) -> None:
    rgb = test_image(1, colour=True, shape=(5, 7))
    stored = convert(rgb)  # type: ignore[operator]
    channels = stored.shape[2]
    out = decode_image(raw(padded(stored.reshape(5, 7 * channels), 4), encoding, step=7 * channels + 4))
    assert out.shape == (5, 7, 3)
    np.testing.assert_array_equal(out, rgb)


def test_ros1_message_decodes_too() -> None:
    grey = test_image(0, colour=False, shape=(5, 7))
    msg = ROS1.types["sensor_msgs/msg/Image"](
        header=header(ROS1, 1),
        height=5,
        width=7,
        encoding="mono8",
        is_bigendian=0,
        step=7,
        data=grey.reshape(-1),
    )
    np.testing.assert_array_equal(decode_image(msg), grey)


def test_compressed_png_and_jpeg() -> None:
    rgb = test_image(2, colour=True)
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    assert ok
    out = decode_image(
        COMPRESSED(header=header(ROS2, 1), format="rgb8; png compressed bgr8", data=png.reshape(-1))
    )
    np.testing.assert_array_equal(out, rgb)
    ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
    out = decode_image(COMPRESSED(header=header(ROS2, 1), format="jpeg", data=jpg.reshape(-1)))
    assert out.shape == rgb.shape
    assert np.abs(out.astype(int) - rgb.astype(int)).mean() < 3.0


def test_compressed_grey_png_stays_grey() -> None:
    grey = test_image(3, colour=False)
    _, png = cv2.imencode(".png", grey)
    out = decode_image(COMPRESSED(header=header(ROS2, 1), format="png", data=png.reshape(-1)))
    np.testing.assert_array_equal(out, grey)


def test_unsupported_encoding_message() -> None:
    msg = raw(np.zeros(70, np.uint8), "yuv422", step=14)
    with pytest.raises(IngestError, match=r"^unsupported image encoding 'yuv422' on /cam/image$"):
        decode_image(msg, "/cam/image")


def test_unsupported_compressed_format() -> None:
    msg = COMPRESSED(header=header(ROS2, 1), format="16UC1; compressedDepth", data=np.zeros(10, np.uint8))
    with pytest.raises(IngestError, match="unsupported compressed image format"):
        decode_image(msg, "/depth")


def test_garbage_compressed_data() -> None:
    msg = COMPRESSED(header=header(ROS2, 1), format="jpeg", data=np.arange(50, dtype=np.uint8))
    with pytest.raises(IngestError, match="cannot decode compressed image"):
        decode_image(msg, "/cam")


def test_short_data_is_corrupt() -> None:
    with pytest.raises(IngestError, match="corrupt image on /cam"):
        decode_image(raw(np.zeros(20, np.uint8), "mono8", step=7), "/cam")

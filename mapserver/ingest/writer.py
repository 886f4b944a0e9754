"""Writing mission logs (used by the simulator and by tests): ROS 1 ``.bag``, standalone ``.db3`` / ``.mcap``.

Messages of the three streams are interleaved in stamp order (``heapq.merge``; at equal stamps odometry
comes first, then ground truth, then the image), and each message's bag receive time is its header stamp.
The input iterables are consumed lazily, so a log of any length is written with bounded memory.

ROS 2 logs are written as a rosbag2 directory (format version 9, ``ROS2_HUMBLE`` message definitions) in a
temporary directory beside the target; for the default standalone form the single storage file is then
moved to the target (``AnyReader`` opens standalone ``.db3`` and ``.mcap`` files: the bag metadata is
embedded in the storage file). With ``directory=True`` the whole rosbag2 directory (``metadata.yaml`` plus
the storage file) becomes the target. ROS 1 bags are written with the ``ROS1_NOETIC`` message definitions.
Every form is written under a temporary name and renamed at the end, so a failure leaves nothing behind;
an existing target is replaced.
"""

from __future__ import annotations

import dataclasses
import heapq
import os
import shutil
import uuid
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import numpy.typing as npt
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from core.se3 import quaternion_from_yaw
from mapserver.ingest.frames import PoseSample

LogFormat = Literal["bag", "db3", "mcap"]
ImageEncoding = Literal["mono8", "mono16", "rgb8", "bgr8", "rgba8", "bgra8", "jpeg", "png"]
GroundTruthType = Literal["odometry", "pose", "pose_cov"]

SUFFIXES: dict[str, str] = {"bag": ".bag", "db3": ".db3", "mcap": ".mcap"}
IMAGE_ENCODINGS = ("mono8", "mono16", "rgb8", "bgr8", "rgba8", "bgra8", "jpeg", "png")
JPEG_QUALITY = 95
ODOM_FRAME = "odom"
BODY_FRAME = "base_link"
CAMERA_FRAME = "camera"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"


ExtraMessage = tuple[int, str, str, Callable[[Any], Any]]
"""A message of any type to write: ``(stamp_ns, topic, msgtype, build)``; ``build(messages)`` returns the
message, given the writer's message helper (``.types``, ``.header(stamp_ns, frame_id)``, ``.vector``, ``.pose``)."""


@dataclass(frozen=True, slots=True)
class OdomSample:
    """One odometry message to write: pose in the odometry frame and body-frame twist.

    Attributes:
        stamp_ns: stamp in nanoseconds.
        x: position x (m).
        y: position y (m).
        z: position z (m).
        yaw: heading (rad); the orientation written is a rotation by ``yaw`` about z.
        vx: forward speed in the body frame (m/s).
        vy: leftward speed (m/s).
        vz: upward speed (m/s).
        wz: yaw rate (rad/s).

    """

    stamp_ns: int
    x: float
    y: float
    z: float
    yaw: float
    vx: float
    vy: float
    vz: float
    wz: float


class _Messages:
    """Builds message objects of one typestore (ROS 1 headers carry ``seq``)."""

    def __init__(self, typestore: Typestore) -> None:
        self.ts = typestore
        self.types = typestore.types
        self.has_seq = "seq" in self.types["std_msgs/msg/Header"].__dataclass_fields__  # type: ignore[attr-defined]  # rosbags types its message classes as plain types
        self.seq = 0

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        time = self.types["builtin_interfaces/msg/Time"](
            sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000)
        )
        header_type = self.types["std_msgs/msg/Header"]
        if self.has_seq:
            self.seq += 1
            return header_type(seq=self.seq, stamp=time, frame_id=frame_id)
        return header_type(stamp=time, frame_id=frame_id)

    def pose(self, x: float, y: float, z: float, q: tuple[float, float, float, float]) -> Any:
        t = self.types
        return t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=float(z)),
            orientation=t["geometry_msgs/msg/Quaternion"](
                x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
            ),
        )

    def vector(self, x: float, y: float, z: float) -> Any:
        return self.types["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))

    def odometry(self, stamp_ns: int, pose: Any, linear: Any, angular: Any) -> Any:
        t = self.types
        return t["nav_msgs/msg/Odometry"](
            header=self.header(stamp_ns, ODOM_FRAME),
            child_frame_id=BODY_FRAME,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=t["geometry_msgs/msg/Twist"](linear=linear, angular=angular), covariance=np.zeros(36)
            ),
        )

    def odom_sample(self, sample: OdomSample, pose_only: bool) -> Any:
        pose = self.pose(sample.x, sample.y, sample.z, quaternion_from_yaw(sample.yaw))
        if pose_only:
            return self.odometry(sample.stamp_ns, pose, self.vector(0, 0, 0), self.vector(0, 0, 0))
        return self.odometry(
            sample.stamp_ns,
            pose,
            self.vector(sample.vx, sample.vy, sample.vz),
            self.vector(0.0, 0.0, sample.wz),
        )

    def ground_truth(self, sample: PoseSample, kind: GroundTruthType) -> Any:
        pose = self.pose(sample.x, sample.y, sample.z, (sample.qx, sample.qy, sample.qz, sample.qw))
        t = self.types
        if kind == "odometry":
            return self.odometry(sample.stamp_ns, pose, self.vector(0, 0, 0), self.vector(0, 0, 0))
        header = self.header(sample.stamp_ns, ODOM_FRAME)
        if kind == "pose":
            return t["geometry_msgs/msg/PoseStamped"](header=header, pose=pose)
        return t["geometry_msgs/msg/PoseWithCovarianceStamped"](
            header=header,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        )

    def image(
        self, stamp_ns: int, pixels: npt.NDArray[Any], encoding: ImageEncoding, jpeg_quality: int = JPEG_QUALITY
    ) -> Any:
        header = self.header(stamp_ns, CAMERA_FRAME)
        if encoding in ("jpeg", "png"):
            return self.types["sensor_msgs/msg/CompressedImage"](
                header=header, format=encoding, data=encode_compressed(pixels, encoding, jpeg_quality)
            )
        data, channels_bytes = raw_image_bytes(pixels, encoding)
        height, width = pixels.shape[:2]
        return self.types["sensor_msgs/msg/Image"](
            header=header,
            height=int(height),
            width=int(width),
            encoding=encoding,
            is_bigendian=0,
            step=int(width * channels_bytes),
            data=data,
        )


def _grey(pixels: npt.NDArray[Any]) -> npt.NDArray[Any]:
    if pixels.ndim == 2:
        return pixels
    return cv2.cvtColor(np.ascontiguousarray(pixels[:, :, :3]), cv2.COLOR_RGB2GRAY)


def _rgb(pixels: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    if pixels.ndim == 2:
        return np.repeat(pixels[:, :, None], 3, axis=2).astype(np.uint8)
    return np.asarray(pixels[:, :, :3], dtype=np.uint8)


def raw_image_bytes(pixels: npt.NDArray[Any], encoding: str) -> tuple[npt.NDArray[np.uint8], int]:
    """Convert pixels to the flat byte array of a raw ``sensor_msgs/Image``.

    Args:
        pixels: uint8 (H, W) grey or (H, W, 3) RGB; ``mono16`` also accepts uint16 (H, W) (a uint8 image is
            scaled by 257 so that ``value >> 8`` gives it back).
        encoding: ``mono8``, ``mono16`` (little-endian), ``rgb8``, ``bgr8``, ``rgba8`` or ``bgra8``.

    Returns:
        ``(data, bytes_per_pixel)``.

    """
    if encoding == "mono8":
        out: npt.NDArray[Any] = np.asarray(_grey(pixels), dtype=np.uint8)
        return np.ascontiguousarray(out).reshape(-1), 1
    if encoding == "mono16":
        grey = _grey(pixels)
        values = grey.astype("<u2") if grey.dtype == np.uint16 else grey.astype("<u2") * 257
        return np.ascontiguousarray(values).view(np.uint8).reshape(-1), 2
    rgb = _rgb(pixels)
    if encoding == "rgb8":
        return np.ascontiguousarray(rgb).reshape(-1), 3
    if encoding == "bgr8":
        return np.ascontiguousarray(rgb[:, :, ::-1]).reshape(-1), 3
    alpha = np.full((*rgb.shape[:2], 1), 255, dtype=np.uint8)
    if encoding == "rgba8":
        return np.ascontiguousarray(np.concatenate([rgb, alpha], axis=2)).reshape(-1), 4
    if encoding == "bgra8":
        return np.ascontiguousarray(np.concatenate([rgb[:, :, ::-1], alpha], axis=2)).reshape(-1), 4
    msg = f"unsupported image encoding {encoding!r} (expected one of {IMAGE_ENCODINGS!r})"
    raise ValueError(msg)


def encode_compressed(
    pixels: npt.NDArray[Any], fmt: Literal["jpeg", "png"], jpeg_quality: int = JPEG_QUALITY
) -> npt.NDArray[np.uint8]:
    """Encode uint8 grey or RGB pixels as JPEG (``jpeg_quality``, 1–100) or PNG bytes."""
    image: npt.NDArray[Any] = np.asarray(pixels, dtype=np.uint8)
    if image.ndim == 3:
        image = cv2.cvtColor(np.ascontiguousarray(image[:, :, :3]), cv2.COLOR_RGB2BGR)
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if fmt == "jpeg" else []
    ok, buffer = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", image, params)
    if not ok:
        msg = f"OpenCV could not encode a {image.shape} image as {fmt}"
        raise ValueError(msg)
    return np.asarray(buffer, dtype=np.uint8).reshape(-1)


def _merged(
    images: Iterable[tuple[int, npt.NDArray[Any]]],
    odometry: Iterable[OdomSample],
    ground_truth: Iterable[PoseSample],
    sonar: Iterable[tuple[int, npt.NDArray[Any]]] = (),
    extra: Iterable[ExtraMessage] = (),
) -> Iterator[tuple[int, int, Any]]:
    """Merge the streams lazily by stamp: ``(stamp_ns, kind, item)``, kind 0 odom, 1 gt, 2 image, 3 sonar, 4 extra."""
    odom_stream = ((int(s.stamp_ns), 0, s) for s in odometry)
    gt_stream = ((int(s.stamp_ns), 1, s) for s in ground_truth)
    image_stream = ((int(stamp), 2, pixels) for stamp, pixels in images)
    sonar_stream = ((int(stamp), 3, pixels) for stamp, pixels in sonar)
    extra_stream = ((int(item[0]), 4, item) for item in extra)
    return heapq.merge(odom_stream, gt_stream, image_stream, sonar_stream, extra_stream, key=lambda e: (e[0], e[1]))


def _target_path(path: Path, fmt: LogFormat, directory: bool) -> Path:
    if fmt not in SUFFIXES:
        msg = f"unknown log format {fmt!r} (expected one of {sorted(SUFFIXES)!r})"
        raise ValueError(msg)
    if directory:
        if fmt == "bag":
            msg = "directory=True is only for the ROS 2 formats db3 and mcap"
            raise ValueError(msg)
        return path
    suffix = SUFFIXES[fmt]
    return path if path.suffix == suffix else path.with_name(path.name + suffix)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def write_log(
    path: str | Path,
    fmt: LogFormat,
    images: Iterable[tuple[int, npt.NDArray[Any]]],
    odometry: Iterable[OdomSample],
    ground_truth: Iterable[PoseSample] = (),
    *,
    image_topic: str = "/robot/camera/image",
    odom_topic: str = "/robot/odom",
    gt_topic: str = "/robot/ground_truth",
    image_encoding: ImageEncoding = "mono8",
    gt_type: GroundTruthType = "pose",
    pose_only_odometry: bool = False,
    directory: bool = False,
    sonar: Iterable[tuple[int, npt.NDArray[Any]]] = (),
    sonar_topic: str = "/robot/sonar/image",
    jpeg_quality: int = JPEG_QUALITY,
    extra: Iterable[ExtraMessage] = (),
) -> Path:
    """Write a mission log.

    Args:
        path: target; the suffix ``.bag``/``.db3``/``.mcap`` is appended when it does not match ``fmt``
            (not for ``directory=True``).
        fmt: ``bag`` (ROS 1), ``db3`` or ``mcap`` (ROS 2).
        images: ``(stamp_ns, pixels)`` in stamp order; uint8 (H, W) grey or (H, W, 3) RGB (converted to the
            encoding: grey ↔ RGB as needed; ``mono16`` stores ``value * 257``).
        odometry: odometry samples in stamp order.
        ground_truth: ground-truth poses in stamp order.
        image_topic: camera topic name.
        odom_topic: odometry topic name (not written when ``odometry`` is empty).
        gt_topic: ground-truth topic name (not written when ``ground_truth`` is empty).
        image_encoding: raw ``sensor_msgs/Image`` encoding, or ``jpeg``/``png`` for ``CompressedImage``.
        gt_type: ``odometry`` (``nav_msgs/Odometry``), ``pose`` (``PoseStamped``) or ``pose_cov``
            (``PoseWithCovarianceStamped``).
        pose_only_odometry: write zero twist (pose only), as many robots do.
        directory: for ``db3``/``mcap``, keep the rosbag2 directory (``metadata.yaml`` + storage file) at
            ``path`` instead of a standalone file.
        sonar: ``(stamp_ns, pixels)`` of a second image stream (mono8 ``sensor_msgs/Image``), in stamp order.
        sonar_topic: its topic name (not written when ``sonar`` is empty).
        jpeg_quality: JPEG quality (1–100) of ``jpeg`` camera frames.
        extra: messages of other topics and types (:data:`ExtraMessage`), in stamp order; at equal stamps
            they come after the other streams' messages.

    Returns:
        The path written.

    Raises:
        ValueError: unknown format or encoding, or ``directory`` with ``bag``.

    """
    options = _checked_options(
        odom_topic, gt_topic, image_topic, sonar_topic, image_encoding, gt_type, pose_only_odometry
    )
    if not 1 <= int(jpeg_quality) <= 100:
        msg = f"jpeg_quality must be 1..100, got {jpeg_quality!r}"
        raise ValueError(msg)
    options = dataclasses.replace(options, jpeg_quality=int(jpeg_quality))
    target = _prepared_target(Path(path), fmt, directory)
    stream = _merged(images, odometry, ground_truth, sonar, extra)
    _write_then_replace(target, fmt, directory, stream, options)
    return target


_GT_TYPES: dict[str, str] = {
    "odometry": "nav_msgs/msg/Odometry",
    "pose": "geometry_msgs/msg/PoseStamped",
    "pose_cov": "geometry_msgs/msg/PoseWithCovarianceStamped",
}


def _image_type(encoding: str) -> str:
    return "sensor_msgs/msg/CompressedImage" if encoding in ("jpeg", "png") else "sensor_msgs/msg/Image"


@dataclass(frozen=True, slots=True)
class _Options:
    topics: dict[int, tuple[str, str]]
    image_encoding: ImageEncoding
    gt_type: GroundTruthType
    pose_only: bool
    jpeg_quality: int = JPEG_QUALITY


def _checked_options(
    odom_topic: str,
    gt_topic: str,
    image_topic: str,
    sonar_topic: str,
    image_encoding: ImageEncoding,
    gt_type: GroundTruthType,
    pose_only: bool,
) -> _Options:
    """Return the writer options (topic and type per stream kind) after checking the encoding and ground-truth type.

    Raises:
        ValueError: unknown image encoding or ground-truth type.
    """
    if image_encoding not in IMAGE_ENCODINGS:
        msg = f"unsupported image encoding {image_encoding!r} (expected one of {IMAGE_ENCODINGS!r})"
        raise ValueError(msg)
    if gt_type not in _GT_TYPES:
        msg = f"unknown ground-truth type {gt_type!r} (expected one of {sorted(_GT_TYPES)!r})"
        raise ValueError(msg)
    return _Options(
        topics={
            0: (odom_topic, "nav_msgs/msg/Odometry"),
            1: (gt_topic, _GT_TYPES[gt_type]),
            2: (image_topic, _image_type(image_encoding)),
            3: (sonar_topic, "sensor_msgs/msg/Image"),
        },
        image_encoding=image_encoding,
        gt_type=gt_type,
        pose_only=pose_only,
    )


def _prepared_target(path: Path, fmt: LogFormat, directory: bool) -> Path:
    """Return the path the log is written to, its parent directory created."""
    target = _target_path(path, fmt, directory)
    target.parent.mkdir(parents=True, exist_ok=True)
    return target


def _write_then_replace(
    target: Path, fmt: LogFormat, directory: bool, stream: Iterator[tuple[int, int, Any]], options: _Options
) -> None:
    """Write the log under a temporary name beside ``target``, then move it there (nothing is left on failure)."""
    temp = target.parent / f".{target.name}.{uuid.uuid4().hex[:12]}.tmp"
    try:
        if fmt == "bag":
            _write_ros1(temp, stream, options)
            built = temp
        else:
            _write_ros2(temp, fmt, stream, options)
            built = temp if directory else temp / f"{temp.name}{SUFFIXES[fmt]}"
        if target.exists() or target.is_symlink():
            _remove(target)
        os.replace(built, target)
    finally:
        if temp.exists() or temp.is_symlink():
            _remove(temp)


def _build(messages: _Messages, stamp: int, kind: int, item: Any, options: _Options) -> Any:
    if kind == 0:
        return messages.odom_sample(item, options.pose_only)
    if kind == 1:
        return messages.ground_truth(item, options.gt_type)
    if kind == 2:
        return messages.image(stamp, item, options.image_encoding, options.jpeg_quality)
    if kind == 4:
        return item[3](messages)
    return messages.image(stamp, item, "mono8")


def _topic_of(kind: int, item: Any, options: _Options) -> tuple[str, str]:
    """Return the (topic, msgtype) a stream item is written to."""
    return (item[1], item[2]) if kind == 4 else options.topics[kind]


def _write_ros1(temp: Path, stream: Iterator[tuple[int, int, Any]], options: _Options) -> None:
    typestore = get_typestore(Stores.ROS1_NOETIC)
    if TF_MESSAGE not in typestore.types:  # ROS 1's tf2_msgs is not in rosbags' Noetic store
        typestore.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_MESSAGE))
    messages = _Messages(typestore)
    with Writer1(temp) as writer:
        connections: dict[str, Any] = {}
        for stamp, kind, item in stream:
            topic, msgtype = _topic_of(kind, item, options)
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
            msg = _build(messages, stamp, kind, item, options)
            writer.write(connections[topic], stamp, typestore.serialize_ros1(msg, msgtype))


def _write_ros2(
    temp: Path, fmt: LogFormat, stream: Iterator[tuple[int, int, Any]], options: _Options
) -> None:
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    messages = _Messages(typestore)
    plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
    with Writer2(temp, version=9, storage_plugin=plugin) as writer:
        connections: dict[str, Any] = {}
        for stamp, kind, item in stream:
            topic, msgtype = _topic_of(kind, item, options)
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
            msg = _build(messages, stamp, kind, item, options)
            writer.write(connections[topic], stamp, typestore.serialize_cdr(msg, msgtype))

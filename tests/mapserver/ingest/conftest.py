"""Shared helpers for the ingest tests: synthetic trajectories, images and small logs built in tmp_path."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from mapserver.ingest.frames import PoseSample
from mapserver.ingest.writer import OdomSample, write_log

T0_NS = 1_700_000_000_000_000_000  # a realistic epoch stamp


def arc_pose(t: float, v: float, w: float) -> tuple[float, float, float]:
    """Pose (x, y, yaw) after t seconds on a constant-velocity arc from the origin heading +x."""
    if abs(w) < 1e-12:
        return v * t, 0.0, 0.0
    yaw = w * t
    return v / w * math.sin(yaw), v / w * (1.0 - math.cos(yaw)), yaw


def arc_odometry(
    n: int, rate_hz: float, v: float = 1.0, w: float = 0.5, t0_ns: int = T0_NS, vz: float = 0.0
) -> list[OdomSample]:
    """Odometry samples (exact pose + constant body twist) on a constant-velocity arc."""
    out = []
    for i in range(n):
        stamp = t0_ns + round(i * 1e9 / rate_hz)
        t = (stamp - t0_ns) * 1e-9
        x, y, yaw = arc_pose(t, v, w)
        out.append(OdomSample(stamp, x, y, vz * t, yaw, v, 0.0, vz, w))
    return out


def varying_odometry(n: int, rate_hz: float, t0_ns: int = T0_NS, seed: int = 0) -> list[OdomSample]:
    """Odometry with changing twist (piecewise constant), poses integrated consistently, irregular stamps."""
    rng = np.random.default_rng(seed)
    out = []
    x = y = yaw = z = 0.0
    stamp = t0_ns
    for _ in range(n):
        v, u, vz, w = (
            rng.uniform(0.2, 1.5),
            rng.uniform(-0.1, 0.1),
            rng.uniform(-0.05, 0.05),
            rng.uniform(-1, 1),
        )
        out.append(OdomSample(stamp, x, y, z, yaw, v, u, vz, w))
        dt_ns = int(1e9 / rate_hz * rng.uniform(0.6, 1.4))
        # advance the pose roughly (the reader integrates twist, so pose consistency is not needed here)
        x += math.cos(yaw) * v * dt_ns * 1e-9
        y += math.sin(yaw) * v * dt_ns * 1e-9
        z += vz * dt_ns * 1e-9
        yaw += w * dt_ns * 1e-9
        stamp += dt_ns
    return out


def test_image(index: int, colour: bool, shape: tuple[int, int] = (24, 32)) -> np.ndarray:
    """A smooth, frame-dependent uint8 image (grey (H, W) or RGB (H, W, 3)); smooth so JPEG stays close."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    base = 128 + 90 * np.sin(xx / 5.0 + index * 0.3) * np.cos(yy / 7.0 - index * 0.2)
    if not colour:
        return np.clip(base, 0, 255).astype(np.uint8)
    channels = [base, 255 - base, 128 + 60 * np.sin((xx + yy) / 9.0 + index)]
    return np.clip(np.stack(channels, axis=2), 0, 255).astype(np.uint8)


test_image.__test__ = False  # type: ignore[attr-defined]  # not a test despite the name


def frame_images(
    n: int, rate_hz: float, colour: bool, t0_ns: int = T0_NS, offset_ns: int = 0
) -> list[tuple[int, np.ndarray]]:
    """``n`` images at ``rate_hz`` starting at ``t0_ns + offset_ns``."""
    return [(t0_ns + offset_ns + round(i * 1e9 / rate_hz), test_image(i, colour)) for i in range(n)]


def identity_gt(samples: Iterable[OdomSample]) -> list[PoseSample]:
    """Ground truth equal to the odometry poses."""
    return [
        PoseSample(s.stamp_ns, s.x, s.y, s.z, 0.0, 0.0, math.sin(s.yaw / 2), math.cos(s.yaw / 2))
        for s in samples
    ]


LogFactory = Callable[..., Path]


@pytest.fixture
def make_log(tmp_path: Path) -> LogFactory:
    """Write a log with :func:`write_log` into tmp_path: ``make_log(name, fmt, images, odometry, ...)``."""

    def factory(
        name: str, fmt: str, images: Any, odometry: Any = (), ground_truth: Any = (), **kw: Any
    ) -> Path:
        return write_log(tmp_path / name, fmt, images, odometry, ground_truth, **kw)  # type: ignore[arg-type]

    return factory


# -- raw multi-topic logs (for topic mapping and error cases) ---------------------------------------------
ROS2 = get_typestore(Stores.ROS2_HUMBLE)
ROS1 = get_typestore(Stores.ROS1_NOETIC)


def ros_time(ts: Any, stamp_ns: int) -> Any:
    return ts.types["builtin_interfaces/msg/Time"](
        sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000
    )


def header(ts: Any, stamp_ns: int) -> Any:
    h = ts.types["std_msgs/msg/Header"]
    if "seq" in h.__dataclass_fields__:
        return h(seq=0, stamp=ros_time(ts, stamp_ns), frame_id="f")
    return h(stamp=ros_time(ts, stamp_ns), frame_id="f")


def image_msg(ts: Any, stamp_ns: int, encoding: str = "mono8", shape: tuple[int, int] = (4, 6)) -> Any:
    channels = {"mono8": 1, "yuv422": 2, "rgb8": 3, "32FC1": 4}.get(encoding, 1)
    h, w = shape
    data = np.arange(h * w * channels, dtype=np.uint8)
    return ts.types["sensor_msgs/msg/Image"](
        header=header(ts, stamp_ns),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=0,
        step=w * channels,
        data=data,
    )


def odometry_msg(ts: Any, stamp_ns: int, vx: float = 0.0) -> Any:
    t = ts.types
    vec = t["geometry_msgs/msg/Vector3"]
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    return t["nav_msgs/msg/Odometry"](
        header=header(ts, stamp_ns),
        child_frame_id="base_link",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](
                linear=vec(x=vx, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0)
            ),
            covariance=np.zeros(36),
        ),
    )


def pose_msg(ts: Any, stamp_ns: int) -> Any:
    t = ts.types
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    return t["geometry_msgs/msg/PoseStamped"](header=header(ts, stamp_ns), pose=pose)


def write_raw(
    path: Path, fmt: str, streams: Sequence[tuple[str, str, Callable[[Any, int], Any], int]]
) -> Path:
    """Write a log with several topics: ``streams`` = [(topic, msgtype, build(ts, stamp) -> msg, count)].

    Messages of a topic are 0.1 s apart starting at T0_NS; ``fmt`` is bag, db3 or mcap (standalone).
    """
    entries = sorted(
        (T0_NS + i * 100_000_000, k, i) for k, (_t, _m, _b, count) in enumerate(streams) for i in range(count)
    )
    if fmt == "bag":
        with Writer1(path) as writer:
            conns = [
                writer.add_connection(topic, msgtype, typestore=ROS1) for topic, msgtype, _b, _c in streams
            ]
            for stamp, k, _i in entries:
                _topic, msgtype, build, _c = streams[k]
                writer.write(conns[k], stamp, ROS1.serialize_ros1(build(ROS1, stamp), msgtype))
        return path
    plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
    bag_dir = path.with_name(path.name + ".d")
    with Writer2(bag_dir, version=9, storage_plugin=plugin) as writer2:
        conns = [writer2.add_connection(topic, msgtype, typestore=ROS2) for topic, msgtype, _b, _c in streams]
        for stamp, k, _i in entries:
            _topic, msgtype, build, _c = streams[k]
            writer2.write(conns[k], stamp, ROS2.serialize_cdr(build(ROS2, stamp), msgtype))
    (bag_dir / f"{bag_dir.name}.{fmt}").rename(path)
    return path

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from core.motion import ZERO_MOTION
from mapserver.errors import IngestError, InputError
from mapserver.ingest import Frame, TopicInfo, map_topics, open_log, parse_topics_arg
from mapserver.ingest.topics import is_truth_like
from tests.mapserver.ingest.conftest import (
    T0_NS,
    LogFactory,
    arc_odometry,
    frame_images,
    identity_gt,
    image_msg,
    odometry_msg,
    pose_msg,
    varying_odometry,
    write_raw,
)

CONTAINERS = ["bag", "db3", "mcap", "dir"]
ENCODINGS = ["mono8", "mono16", "rgb8", "bgr8", "rgba8", "bgra8", "jpeg", "png"]
GREY = {"mono8", "mono16"}


def build(
    make_log: LogFactory, name: str, container: str, images: object, odometry: object = (), **kw: object
) -> Path:
    if container == "dir":
        return make_log(name, "db3", images, odometry, directory=True, **kw)
    return make_log(name, container, images, odometry, **kw)


def read_frames(path: Path, **kw: object) -> list[Frame]:
    with open_log(path, **kw) as log:  # type: ignore[arg-type]
        return list(log.frames())


# -- containers x encodings ------------------------------------------------------------------------------
@pytest.mark.parametrize("encoding", ENCODINGS)
@pytest.mark.parametrize("container", CONTAINERS)
def test_every_container_and_encoding_decodes(make_log: LogFactory, container: str, encoding: str) -> None:
    colour = encoding not in GREY
    images = frame_images(3, 10.0, colour=colour)
    path = build(make_log, "log", container, images, arc_odometry(5, 20.0), image_encoding=encoding)
    frames = read_frames(path)
    assert [f.stamp_ns for f in frames] == [s for s, _ in images]
    for frame, (_stamp, expected) in zip(frames, images, strict=True):
        assert frame.image.dtype == np.uint8
        assert frame.image.shape == expected.shape
        if encoding == "jpeg":
            diff = np.abs(frame.image.astype(int) - expected.astype(int))
            assert diff.mean() < 3.0 and diff.max() < 40
        else:
            np.testing.assert_array_equal(frame.image, expected)


@pytest.mark.parametrize("pose_only", [False, True])
def test_identical_frames_across_containers(make_log: LogFactory, pose_only: bool) -> None:
    images = frame_images(12, 9.0, colour=False, offset_ns=3_000_000)
    odometry = varying_odometry(60, 33.0)
    sequences = {
        c: read_frames(build(make_log, f"log_{c}", c, images, odometry, pose_only_odometry=pose_only))
        for c in CONTAINERS
    }
    ref = sequences["bag"]
    assert len(ref) == 12
    assert ref[0].motion == ZERO_MOTION
    assert any(abs(f.motion.dx) > 0.01 for f in ref[1:])  # type: ignore[union-attr]
    for container, frames in sequences.items():
        assert [f.stamp_ns for f in frames] == [f.stamp_ns for f in ref], container
        for a, b in zip(frames, ref, strict=True):
            assert a.motion is not None and b.motion is not None
            got = (a.motion.dx, a.motion.dy, a.motion.dz, a.motion.dyaw, a.motion.dt)
            want = (b.motion.dx, b.motion.dy, b.motion.dz, b.motion.dyaw, b.motion.dt)
            assert got == pytest.approx(want, abs=1e-9), container
            np.testing.assert_array_equal(a.image, b.image)


def test_pose_only_odometry_matches_twist_on_arc(make_log: LogFactory) -> None:
    # odometry at 40 Hz, frames at 10 Hz on odometry stamps (pose interpolation is then exact on the arc)
    odometry = arc_odometry(48, 40.0, v=1.0, w=0.5, vz=0.05)
    images = frame_images(11, 10.0, colour=False)
    with open_log(make_log("twist", "mcap", images, odometry)) as log:
        assert log.odometry_mode == "twist"
        twist = list(log.frames())
    with open_log(make_log("pose", "mcap", images, odometry, pose_only_odometry=True)) as log:
        assert log.odometry_mode == "pose"
        pose = list(log.frames())
    for a, b in zip(twist[1:], pose[1:], strict=True):
        assert a.motion is not None and b.motion is not None
        assert (a.motion.dx, a.motion.dy, a.motion.dz, a.motion.dyaw, a.motion.dt) == pytest.approx(
            (b.motion.dx, b.motion.dy, b.motion.dz, b.motion.dyaw, b.motion.dt), abs=1e-6
        )
    # 0.1 s at v = 1, ω = 0.5: the arc
    m = twist[1].motion
    assert m is not None
    assert (m.dx, m.dy, m.dyaw) == pytest.approx((np.sin(0.05) / 0.5, (1 - np.cos(0.05)) / 0.5, 0.05))


def test_odometry_mode_can_be_forced(make_log: LogFactory) -> None:
    path = make_log("log", "db3", frame_images(3, 10.0, False), arc_odometry(10, 20.0))
    with open_log(path, odometry_mode="pose") as log:
        assert log.odometry_mode == "pose"


def test_no_odometry_gives_none_motion(make_log: LogFactory) -> None:
    frames = read_frames(make_log("log", "bag", frame_images(3, 10.0, True), (), image_encoding="png"))
    assert [f.motion for f in frames] == [None, None, None]


def test_frames_start_stop_resume(make_log: LogFactory) -> None:
    path = make_log("log", "bag", frame_images(10, 10.0, False), varying_odometry(40, 25.0))
    with open_log(path) as log:
        assert log.count_frames() == 10
        whole = list(log.frames())
        parts = list(log.frames(0, 4)) + list(log.frames(4, 7)) + list(log.frames(start=7))
    assert [f.stamp_ns for f in parts] == [f.stamp_ns for f in whole]
    assert [f.motion for f in parts] == [f.motion for f in whole]
    assert parts[4].motion != ZERO_MOTION


@pytest.mark.parametrize("gt_type", ["odometry", "pose", "pose_cov"])
def test_ground_truth_round_trip(make_log: LogFactory, gt_type: str) -> None:
    odometry = arc_odometry(8, 10.0)
    gt = identity_gt(odometry)
    path = make_log("log", "bag", frame_images(3, 10.0, False), odometry, gt, gt_type=gt_type)
    with open_log(path) as log:
        assert log.mapping.ground_truth == "/robot/ground_truth"
        assert log.mapping.odometry == "/robot/odom"
        got = list(log.ground_truth())
    assert [g.stamp_ns for g in got] == [g.stamp_ns for g in gt]
    for a, b in zip(got, gt, strict=True):
        assert (a.x, a.y, a.z, a.qx, a.qy, a.qz, a.qw) == pytest.approx(
            (b.x, b.y, b.z, b.qx, b.qy, b.qz, b.qw)
        )


def test_metadata_and_sha256(make_log: LogFactory, tmp_path: Path) -> None:
    path = make_log("log", "mcap", frame_images(5, 10.0, False), arc_odometry(9, 20.0))
    with open_log(path) as log:
        assert log.path == path
        assert log.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
        assert log.duration_s == pytest.approx(0.4, abs=1e-6)
        by_name = {t.name: t for t in log.topics}
        assert by_name["/robot/camera/image"].msgtype == "sensor_msgs/msg/Image"
        assert by_name["/robot/camera/image"].count == 5
        assert by_name["/robot/odom"].rate_hz == pytest.approx(20.0, rel=1e-6)
    folder = make_log("dir", "db3", frame_images(2, 10.0, False), directory=True)
    with open_log(folder) as log:
        digest = hashlib.sha256()
        for f in sorted(p for p in folder.rglob("*") if p.is_file()):
            digest.update(f.read_bytes())
        assert log.sha256 == digest.hexdigest()


def test_header_stamp_zero_falls_back_to_receive_time(tmp_path: Path) -> None:
    path = write_raw(
        tmp_path / "zero.db3",
        "db3",
        [("/cam/image", "sensor_msgs/msg/Image", lambda ts, _s: image_msg(ts, 0), 3)],
    )
    frames = read_frames(path)
    assert [f.stamp_ns for f in frames] == [T0_NS, T0_NS + 100_000_000, T0_NS + 200_000_000]


# -- topic mapping -------------------------------------------------------------------------------------
def info(name: str, msgtype: str, count: int) -> TopicInfo:
    return TopicInfo(name, msgtype, count, 0.0)


IMG, CIMG, ODOM = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "nav_msgs/msg/Odometry"
POSE, POSECOV = "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped"


def test_mapping_rules() -> None:
    topics = [
        info("/a/feed", IMG, 10),
        info("/z/camera/compressed", CIMG, 10),  # tie on count: the camera-like name wins
        info("/cam/depth/image", IMG, 50),  # depth is only a fallback
        info("/empty/image", IMG, 0),
        info("/wheel/odom", ODOM, 100),
        info("/ekf/odom", ODOM, 100),  # tie: alphabetical
        info("/robot/ground_truth", ODOM, 500),
        info("/mocap/pose", POSE, 10),
    ]
    m = map_topics(topics)
    assert (m.image, m.odometry, m.ground_truth) == (
        "/z/camera/compressed",
        "/ekf/odom",
        "/robot/ground_truth",
    )
    assert map_topics([info("/b/x", IMG, 3), info("/a/x", IMG, 3)]).image == "/a/x"
    assert map_topics([info("/cam/depth", IMG, 3)]).image == "/cam/depth"
    # the only PoseStamped topic is the ground truth when no truth-like name exists
    assert map_topics([info("/cam", IMG, 1), info("/robot/pose", POSECOV, 4)]).ground_truth == "/robot/pose"
    assert map_topics([info("/cam", IMG, 1), info("/p1", POSE, 4), info("/p2", POSE, 4)]).ground_truth is None


def test_truth_like_names() -> None:
    for name in (
        "/robot/ground_truth",
        "/GroundTruth/odom",
        "/gt",
        "/odom_gt",
        "/robot/gt/odom",
        "/vicon/base",
        "/overhead_cam/pose",
    ):
        assert is_truth_like(name), name
    for name in ("/robot/odom", "/lengths/odom", "/right/odom"):
        assert not is_truth_like(name), name


def test_auto_mapping_and_overrides_on_a_real_log(tmp_path: Path) -> None:
    streams = [
        ("/robot/camera/image", IMG, lambda ts, s: image_msg(ts, s), 6),
        ("/other/image", IMG, lambda ts, s: image_msg(ts, s), 4),
        ("/robot/odom", ODOM, lambda ts, s: odometry_msg(ts, s, vx=1.0), 8),
        ("/robot/odom_gt", ODOM, lambda ts, s: odometry_msg(ts, s), 12),
        ("/robot/pose", POSE, pose_msg, 3),
    ]
    path = write_raw(tmp_path / "multi.bag", "bag", streams)
    with open_log(path) as log:
        assert log.mapping.as_dict() == {
            "image": "/robot/camera/image",
            "odometry": "/robot/odom",
            "ground_truth": "/robot/odom_gt",
        }
    overrides = parse_topics_arg("image=/other/image, odometry=none,ground_truth=/robot/pose")
    with open_log(path, overrides) as log:
        assert log.mapping.as_dict() == {
            "image": "/other/image",
            "odometry": None,
            "ground_truth": "/robot/pose",
        }
        assert log.count_frames() == 4
        assert all(f.motion is None for f in log.frames())
        assert [g.x for g in log.ground_truth()] == [1.0, 1.0, 1.0]
    with pytest.raises(IngestError, match="unknown topic key 'lidar'"):
        open_log(path, {"lidar": "/lidar"})
    with pytest.raises(IngestError, match="'/nope' given for 'odometry' is not in the log"):
        open_log(path, {"odometry": "/nope"})
    with pytest.raises(IngestError, match="'/robot/pose' given for 'image' has type"):
        open_log(path, {"image": "/robot/pose"})


def test_parse_topics_arg() -> None:
    assert parse_topics_arg("image=/a,odometry=/b") == {"image": "/a", "odometry": "/b"}
    assert parse_topics_arg("ground_truth=") == {"ground_truth": ""}
    for bad in ("image", "=/a", "image=/a,image=/b", ",", ""):
        with pytest.raises(InputError):
            parse_topics_arg(bad)


# -- errors ---------------------------------------------------------------------------------------------
def one_line(err: pytest.ExceptionInfo[IngestError]) -> str:
    text = str(err.value)
    assert "\n" not in text
    return text


def test_missing_path(tmp_path: Path) -> None:
    with pytest.raises(IngestError, match="log not found") as err:
        open_log(tmp_path / "nope.bag")
    assert str(tmp_path / "nope.bag") in one_line(err)


def test_text_file_renamed_bag(tmp_path: Path) -> None:
    path = tmp_path / "notes.bag"
    path.write_text("this is not a bag\n" * 20)
    with pytest.raises(IngestError, match="not a readable bag") as err:
        open_log(path)
    assert str(path) in one_line(err)


@pytest.mark.parametrize("fmt", ["bag", "db3", "mcap"])
def test_truncated_log(make_log: LogFactory, fmt: str) -> None:
    path = make_log("log", fmt, frame_images(40, 10.0, True), arc_odometry(80, 20.0), image_encoding="rgb8")
    data = path.read_bytes()
    cut = path.with_name(f"cut.{fmt}")
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(IngestError) as err, open_log(cut) as log:
        list(log.frames())
    assert str(cut) in one_line(err)


def test_directory_without_metadata_and_unknown_suffix(tmp_path: Path) -> None:
    (tmp_path / "folder").mkdir()
    with pytest.raises(IngestError, match=r"no metadata\.yaml"):
        open_log(tmp_path / "folder")
    (tmp_path / "log.txt").write_text("x")
    with pytest.raises(IngestError, match=r"expected a \.bag, \.db3 or \.mcap"):
        open_log(tmp_path / "log.txt")


@pytest.mark.parametrize("fmt", ["bag", "mcap"])
def test_only_odometry_has_no_camera(make_log: LogFactory, fmt: str) -> None:
    path = make_log("odom_only", fmt, [], arc_odometry(10, 20.0))
    with pytest.raises(IngestError, match="no camera topic: process needs sensor_msgs/Image or CompressedImage") as err:
        open_log(path)
    assert str(path) in one_line(err)


@pytest.mark.parametrize("fmt", ["bag", "db3"])
def test_unsupported_encoding_at_open(tmp_path: Path, fmt: str) -> None:
    path = write_raw(
        tmp_path / f"yuv.{fmt}", fmt, [("/cam/image", IMG, lambda ts, s: image_msg(ts, s, "yuv422"), 3)]
    )
    with pytest.raises(IngestError, match="unsupported image encoding 'yuv422' on /cam/image") as err:
        open_log(path)
    assert str(path) in one_line(err)


def test_closed_log_raises(make_log: LogFactory) -> None:
    path = make_log("log", "db3", frame_images(2, 10.0, False))
    log = open_log(path)
    log.close()
    log.close()
    with pytest.raises(IngestError, match="closed"):
        list(log.frames())


def test_out_of_order_receive_gives_stamp_ordered_frames(tmp_path: Path) -> None:
    # images arrive every 0.1 s but their header stamps are 0, 0.2, 0.1, 0.3 s; odometry: 1 m/s forward
    shuffled = {0: 0, 1: 2, 2: 1, 3: 3}

    def image(ts: object, stamp: int) -> object:
        return image_msg(ts, T0_NS + shuffled[(stamp - T0_NS) // 100_000_000] * 100_000_000)

    streams = [
        ("/cam/image", IMG, image, 4),
        ("/odom", ODOM, lambda ts, s: odometry_msg(ts, s, vx=1.0), 5),
    ]
    frames = read_frames(write_raw(tmp_path / "shuffled.mcap", "mcap", streams))
    assert [(f.stamp_ns - T0_NS) // 100_000_000 for f in frames] == [0, 1, 2, 3]
    assert [round(f.motion.dx, 9) for f in frames] == [0.0, 0.1, 0.1, 0.1]  # type: ignore[union-attr]
    assert [round(f.motion.dt, 9) for f in frames] == [0.0, 0.1, 0.1, 0.1]  # type: ignore[union-attr]


@pytest.mark.parametrize("fmt", ["bag", "mcap"])
def test_frames_and_ground_truth_can_be_interleaved(make_log: LogFactory, fmt: str) -> None:
    odometry = arc_odometry(40, 20.0)
    path = make_log("log", fmt, frame_images(20, 10.0, False), odometry, identity_gt(odometry))
    with open_log(path) as log:
        alone = ([f.stamp_ns for f in log.frames()], [g.stamp_ns for g in log.ground_truth()])
        frames, gt = log.frames(), log.ground_truth()
        mixed: tuple[list[int], list[int]] = ([], [])
        for f, g in zip(frames, gt, strict=False):
            mixed[0].append(f.stamp_ns)
            mixed[1].append(g.stamp_ns)
        mixed[1].extend(g.stamp_ns for g in gt)
    assert mixed == alone

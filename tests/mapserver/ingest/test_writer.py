from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from mapserver.ingest import OdomSample, open_log, write_log
from tests.mapserver.ingest.conftest import T0_NS, arc_odometry, frame_images, identity_gt


def read_all(path: Path) -> list[tuple[str, int, object]]:
    with AnyReader([path]) as reader:
        return [(c.topic, t, reader.deserialize(raw, c.msgtype)) for c, t, raw in reader.messages()]


@pytest.mark.parametrize("fmt", ["bag", "db3", "mcap"])
def test_interleaved_in_stamp_order_with_header_stamps(tmp_path: Path, fmt: str) -> None:
    odometry = arc_odometry(13, 30.0)
    path = write_log(
        tmp_path / f"log.{fmt}", fmt, frame_images(4, 10.0, False), odometry, identity_gt(odometry[::3])
    )  # type: ignore[arg-type]
    assert path == tmp_path / f"log.{fmt}" and path.is_file()
    messages = read_all(path)
    stamps = [t for _topic, t, _msg in messages]
    assert stamps == sorted(stamps)
    counts = {topic: sum(1 for t, _s, _m in messages if t == topic) for topic, _s, _m in messages}
    assert counts == {"/robot/camera/image": 4, "/robot/odom": 13, "/robot/ground_truth": 5}
    for _topic, t, msg in messages:
        header = msg.header  # type: ignore[attr-defined]
        assert header.stamp.sec * 1_000_000_000 + header.stamp.nanosec == t


def test_suffix_is_appended_and_target_replaced(tmp_path: Path) -> None:
    first = write_log(tmp_path / "session1", "mcap", frame_images(2, 10.0, False), [])
    assert first == tmp_path / "session1.mcap"
    second = write_log(tmp_path / "session1", "mcap", frame_images(3, 10.0, False), [])
    assert second == first
    with open_log(second) as log:
        assert log.count_frames() == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["session1.mcap"]


def test_directory_form(tmp_path: Path) -> None:
    path = write_log(tmp_path / "bagdir", "mcap", frame_images(2, 10.0, False), [], directory=True)
    assert path.is_dir() and (path / "metadata.yaml").is_file()
    with open_log(path) as log:
        assert log.count_frames() == 2
    with pytest.raises(ValueError, match="directory=True"):
        write_log(tmp_path / "x", "bag", [], [], directory=True)


def test_streams_are_consumed_lazily(tmp_path: Path) -> None:
    pulled: list[int] = []

    def images() -> Iterator[tuple[int, np.ndarray]]:
        for stamp, pixels in frame_images(5, 10.0, False):
            pulled.append(stamp)
            yield stamp, pixels

    odometry = iter(arc_odometry(10, 20.0))
    path = write_log(tmp_path / "lazy", "db3", images(), odometry)
    assert len(pulled) == 5
    with open_log(path) as log:
        assert log.count_frames() == 5 and log.mapping.odometry == "/robot/odom"


@pytest.mark.parametrize("fmt", ["bag", "db3", "mcap"])
def test_failure_leaves_nothing(tmp_path: Path, fmt: str) -> None:
    def images() -> Iterator[tuple[int, np.ndarray]]:
        yield T0_NS, np.zeros((4, 4), np.uint8)
        msg = "camera died"
        raise RuntimeError(msg)

    with pytest.raises(RuntimeError, match="camera died"):
        write_log(tmp_path / "broken", fmt, images(), arc_odometry(3, 10.0))  # type: ignore[arg-type]
    assert list(tmp_path.iterdir()) == []


def test_pose_only_writes_zero_twist(tmp_path: Path) -> None:
    path = write_log(
        tmp_path / "p", "bag", frame_images(2, 10.0, False), arc_odometry(3, 10.0), pose_only_odometry=True
    )
    odoms = [m for topic, _t, m in read_all(path) if topic == "/robot/odom"]
    assert len(odoms) == 3
    for msg in odoms:
        twist = msg.twist.twist  # type: ignore[attr-defined]
        assert (twist.linear.x, twist.angular.z) == (0.0, 0.0)
    assert odoms[-1].pose.pose.position.x > 0.0  # type: ignore[attr-defined]


def test_odom_sample_fields_round_trip(tmp_path: Path) -> None:
    sample = OdomSample(T0_NS, 1.0, 2.0, 3.0, 0.7, 0.5, 0.1, -0.2, 0.3)
    path = write_log(tmp_path / "o", "mcap", frame_images(1, 10.0, False), [sample])
    (msg,) = [m for topic, _t, m in read_all(path) if topic == "/robot/odom"]
    p, t = msg.pose.pose, msg.twist.twist  # type: ignore[attr-defined]
    assert (p.position.x, p.position.y, p.position.z) == (1.0, 2.0, 3.0)
    assert (p.orientation.z, p.orientation.w) == pytest.approx((np.sin(0.35), np.cos(0.35)))
    assert (t.linear.x, t.linear.y, t.linear.z, t.angular.z) == (0.5, 0.1, -0.2, 0.3)


def test_custom_topics_and_colour_to_grey(tmp_path: Path) -> None:
    path = write_log(
        tmp_path / "c",
        "db3",
        frame_images(2, 10.0, True),
        [],
        image_topic="/cam/left",
        image_encoding="mono8",
    )
    with open_log(path) as log:
        assert log.mapping.image == "/cam/left"
        frames = list(log.frames())
    assert frames[0].image.ndim == 2


def test_bad_arguments(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unsupported image encoding"):
        write_log(tmp_path / "x", "bag", [], [], image_encoding="yuv422")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown log format"):
        write_log(tmp_path / "x", "zip", [], [])  # type: ignore[arg-type]

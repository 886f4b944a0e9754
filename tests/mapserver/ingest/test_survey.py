"""``inspect`` shows any readable log: topics with counts, rates and spans; what ``process`` lacks (exit 0)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapserver.cli import main
from tests.mapserver.ingest.conftest import (
    T0_NS,
    LogFactory,
    arc_odometry,
    frame_images,
    header,
    identity_gt,
    image_msg,
    write_raw,
)

NO_CAMERA = "no camera topic: process needs sensor_msgs/Image or CompressedImage"


def _inspect(path: Path, capsys: pytest.CaptureFixture[str], *extra: str) -> tuple[int, dict[str, Any], str]:
    code = main(["inspect", str(path), "--json", *extra])
    out, err = capsys.readouterr()
    return code, json.loads(out.strip().splitlines()[-1]), err


def imu_msg(ts: Any, stamp_ns: int) -> Any:
    t = ts.types
    vec = t["geometry_msgs/msg/Vector3"]
    return t["sensor_msgs/msg/Imu"](
        header=header(ts, stamp_ns),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9),
        angular_velocity=vec(x=0.0, y=0.0, z=0.1),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=vec(x=0.0, y=0.0, z=9.81),
        linear_acceleration_covariance=np.zeros(9),
    )


@pytest.mark.parametrize("fmt", ["bag", "db3", "mcap"])
def test_a_log_with_only_odometry_is_listed_with_what_is_missing(
    make_log: LogFactory, fmt: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # 21 odometry messages at 20 Hz (arc_odometry: 0.05 s apart from T0_NS): span 1.0 s, rate 20 Hz
    path = make_log("odom_only", fmt, [], arc_odometry(21, 20.0))
    code, result, err = _inspect(path, capsys)
    assert code == 0
    assert result["usable"] is False and result["missing"] == ["image"]
    assert result["reasons"] == {"image": NO_CAMERA}
    assert result["mapping"] == {"image": None, "odometry": "/robot/odom", "ground_truth": None}
    (topic,) = result["topics"]
    assert (topic["name"], topic["type"], topic["count"]) == ("/robot/odom", "nav_msgs/msg/Odometry", 21)
    assert topic["span_s"] == pytest.approx(1.0, abs=1e-9) and topic["rate_hz"] == pytest.approx(20.0, abs=1e-3)
    assert (topic["first_s"], topic["last_s"]) == (0.0, pytest.approx(1.0, abs=1e-9))
    assert result["frames"] == 0 and result["odometry_mode"] is None
    assert f"image: {NO_CAMERA}" in err and "usable by process: no (missing: image)" in err
    # process still refuses it: exit 2, one line
    assert main(["process", str(path)]) == 2
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert out == "" and len(lines) == 1 and NO_CAMERA in lines[0] and lines[0].startswith("ERROR: ")


@pytest.mark.parametrize("fmt", ["bag", "mcap"])
def test_a_log_with_only_imu_lists_the_imu_topic(tmp_path: Path, fmt: str, capsys: pytest.CaptureFixture[str]) -> None:
    # write_raw puts messages 0.1 s apart: 31 messages span 3.0 s at 10 Hz
    path = write_raw(tmp_path / f"imu.{fmt}", fmt, [("/imu/data", "sensor_msgs/msg/Imu", imu_msg, 31)])
    code, result, _err = _inspect(path, capsys)
    assert code == 0 and result["usable"] is False and result["missing"] == ["image"]
    assert result["topics"] == [
        {"name": "/imu/data", "type": "sensor_msgs/msg/Imu", "count": 31, "rate_hz": 10.0, "first_s": 0.0,
         "last_s": 3.0, "span_s": 3.0}
    ]  # fmt: skip
    assert result["duration_s"] == 3.0 and result["start_time_s"] == pytest.approx(T0_NS * 1e-9)
    assert any(note.startswith("no odometry topic") for note in result["notes"])


def test_spans_are_per_topic_and_a_usable_log_has_nothing_missing(
    make_log: LogFactory, capsys: pytest.CaptureFixture[str]
) -> None:
    # 11 frames at 10 Hz (1.0 s) and 21 odometry messages at 20 Hz (1.0 s), ground truth = odometry stamps
    odometry = arc_odometry(21, 20.0)
    path = make_log("full", "bag", frame_images(11, 10.0, False), odometry, identity_gt(odometry))
    code, result, err = _inspect(path, capsys)
    assert code == 0 and result["usable"] is True and result["missing"] == [] and result["reasons"] == {}
    assert result["odometry_mode"] == "twist" and result["frames"] == 11 and result["notes"] == []
    rates = {t["name"]: t["rate_hz"] for t in result["topics"]}
    assert rates == {"/robot/camera/image": 10.0, "/robot/odom": 20.0, "/robot/ground_truth": 20.0}
    assert "usable by process: yes" in err


def test_an_image_topic_that_does_not_decode_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def depth(ts: Any, stamp: int) -> Any:
        return image_msg(ts, stamp, "32FC1")

    path = write_raw(tmp_path / "float.bag", "bag", [("/camera/image", "sensor_msgs/msg/Image", depth, 3)])
    code, result, _err = _inspect(path, capsys)
    assert code == 0 and result["usable"] is False and result["missing"] == ["image"]
    assert result["mapping"]["image"] == "/camera/image"
    assert "32FC1" in result["reasons"]["image"]


def test_unreadable_logs_and_bad_overrides_still_exit_2(
    make_log: LogFactory, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    empty = tmp_path / "empty.bag"
    empty.write_bytes(b"")
    path = make_log("odom_only", "bag", [], arc_odometry(5, 20.0))
    for argv in (["inspect", str(empty)], ["inspect", str(path), "--topics", "image=/robot/odom"]):
        assert main(argv) == 2
        out, err = capsys.readouterr()
        assert out == "" and len(err.strip().splitlines()) == 1

"""``inspect``'s recommendation: the preset and the settings a log decides (field of view, rate, size, panorama)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1

from core import load_config, preset
from mapserver.cli import main
from mapserver.ingest.camera import camera_info_topic, pinhole_fov_deg
from tests.mapserver.ingest.conftest import ROS1, T0_NS, header, image_msg, odometry_msg, write_raw


def _inspect(path: Path, capsys: pytest.CaptureFixture[str], *extra: str) -> tuple[dict[str, Any], str]:
    assert main(["inspect", str(path), "--json", *extra]) == 0
    out, err = capsys.readouterr()
    return json.loads(out.strip().splitlines()[-1]), err


def _info(width: int, fx: float) -> Any:
    def build(ts: Any, stamp: int) -> Any:
        t = ts.types
        upper = "K" in t["sensor_msgs/msg/CameraInfo"].__dataclass_fields__  # ROS 1 spells the matrices D, K, R, P
        k = np.array([fx, 0.0, width / 2, 0.0, fx, 24.0, 0.0, 0.0, 1.0])
        matrices = {"d": np.zeros(5), "k": k, "r": np.eye(3).ravel(), "p": np.zeros(12)}
        roi = t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return t["sensor_msgs/msg/CameraInfo"](
            header=header(ts, stamp), height=48, width=width, distortion_model="plumb_bob", binning_x=0,
            binning_y=0, roi=roi, **{(key.upper() if upper else key): value for key, value in matrices.items()},
        )  # fmt: skip

    return build


def _camera(shape: tuple[int, int]) -> Any:
    return lambda ts, stamp: image_msg(ts, stamp, "mono8", shape)


def _odometry(ts: Any, stamp: int) -> Any:
    return odometry_msg(ts, stamp, vx=0.5)


def _log(tmp_path: Path, fmt: str, shape: tuple[int, int], info: Any = None, odometry: bool = True) -> Path:
    """Frames at 10 Hz (write_raw: 0.1 s apart), odometry at 10 Hz, and a CameraInfo topic when ``info``."""
    streams = [("/cam/image_raw", "sensor_msgs/msg/Image", _camera(shape), 12)]
    if odometry:
        streams.append(("/odom", "nav_msgs/msg/Odometry", _odometry, 12))
    if info is not None:
        streams.append(("/cam/camera_info", "sensor_msgs/msg/CameraInfo", info, 12))
    return write_raw(tmp_path / f"log.{fmt}", fmt, streams)


def test_the_pinhole_field_of_view_and_the_camera_info_topic_chosen() -> None:
    # 2·atan(64 / (2·32)) = 2·45° = 90°; 2·atan(160 / (2·104.26)) = 2·37.5° = 75°
    assert pinhole_fov_deg(64, 32) == pytest.approx(90.0)
    assert pinhole_fov_deg(160, 80 / math.tan(math.radians(37.5))) == pytest.approx(75.0)
    assert pinhole_fov_deg(64, 0.0) is None and pinhole_fov_deg(0, 32) is None  # uncalibrated
    info = "sensor_msgs/msg/CameraInfo"
    topics = [("/left/camera_info", info), ("/right/camera_info", info), ("/right/image", "x")]
    assert camera_info_topic(topics, "/right/image") == "/right/camera_info"  # the image's namespace
    assert camera_info_topic(topics, "/front/image") is None  # two elsewhere: neither
    assert camera_info_topic(topics[:1], "/front/image") == "/left/camera_info"  # the only one


@pytest.mark.parametrize("fmt", ["bag", "mcap"])
def test_a_camera_info_gives_the_field_of_view_and_the_forward_preset(
    tmp_path: Path, fmt: str, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _log(tmp_path, fmt, (48, 64), _info(64, 32.0))
    result, err = _inspect(path, capsys, "--ini", str(tmp_path / "rec.ini"))
    rec = result["recommendation"]
    assert rec["camera"] == {
        "width": 64, "height": 48, "fov_deg": pytest.approx(90.0), "fov_source": "/cam/camera_info",
        "panoramic": False, "panoramic_from": "fov", "camera_hz": 10.0, "odometry_hz": 10.0,
    }  # fmt: skip
    assert rec["preset"] == "forward" and rec["needs"] == [] and rec["notes"] == []
    # forward's 60 × 20 template fits a 64 × 48 image
    assert rec["settings"] == {"camera_fov_deg": 90.0, "camera_hz": 10.0, "template_x_size": 60,
                               "template_y_size": 20, "vt_panoramic": False}  # fmt: skip
    assert rec["set"] == "camera_fov_deg=90,camera_hz=10,template_x_size=60,template_y_size=20,vt_panoramic=0"
    expected = preset("forward").replace(camera_fov_deg=90.0)
    assert load_config(tmp_path / "rec.ini") == expected  # the INI written is the preset with the settings
    assert (tmp_path / "rec.ini").read_text() == rec["ini"]
    assert f"--preset forward --set {rec['set']}" in err and "field of view 90° (from /cam/camera_info)" in err
    # --fov wins over the CameraInfo
    result, _err = _inspect(path, capsys, "--fov", "60")
    assert result["recommendation"]["camera"]["fov_source"] == "--fov"
    assert result["recommendation"]["settings"]["camera_fov_deg"] == 60.0


def test_without_a_camera_info_inspect_asks_for_the_field_of_view(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _log(tmp_path, "bag", (48, 64), odometry=False)
    result, err = _inspect(path, capsys)
    rec = result["recommendation"]
    assert rec["preset"] == "forward" and rec["needs"] == ["fov"] and rec["camera"]["fov_deg"] is None
    assert "camera_fov_deg" not in rec["settings"]
    need = next(line for line in err.splitlines() if line.startswith("need: "))
    assert "--fov DEG" in need and "--set camera_fov_deg=DEG" in need
    assert any(note.startswith("no odometry topic: process runs visual odometry") for note in rec["notes"])
    # given, the need goes
    result, err = _inspect(path, capsys, "--fov", "75")
    assert result["recommendation"]["needs"] == [] and "need: " not in err


def test_a_wide_strip_is_taken_for_a_panorama_and_gets_circle(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # 64 × 16: four times as wide as high, no CameraInfo: a 360° strip; circle's 128 × 32 template clipped to it
    path = _log(tmp_path, "bag", (16, 64))
    rec = _inspect(path, capsys)[0]["recommendation"]
    assert rec["preset"] == "circle" and rec["needs"] == []
    assert rec["camera"]["panoramic"] is True and rec["camera"]["panoramic_from"] == "aspect"
    assert (rec["camera"]["fov_deg"], rec["camera"]["fov_source"]) == (360.0, "aspect")
    settings = rec["settings"]
    assert (settings["template_x_size"], settings["template_y_size"]) == (64, 16)
    assert settings["vt_panoramic"] is False  # circle's, measured (core/config/_presets.py)
    # not the Virtual Tour's 256 × 64: the visual-odometry windows are the whole image
    windows = ("vtrans_image_x_max", "vtrans_image_y_max", "vrot_image_x_max", "vrot_image_y_max")
    assert all(settings[key] == -1 for key in windows)
    ini = tmp_path / "circle.ini"
    ini.write_text(rec["ini"])
    assert load_config(ini) == preset("circle").replace(**settings)  # 'openratslam_parts =' (none) reads back
    # a 4:3 image of the same log family stays forward; a 360° --fov makes it circle
    (tmp_path / "f").mkdir()
    forward = _log(tmp_path / "f", "bag", (48, 64))
    assert _inspect(forward, capsys)[0]["recommendation"]["preset"] == "forward"
    assert _inspect(forward, capsys, "--fov", "360")[0]["recommendation"]["preset"] == "circle"


def test_an_unusable_log_gets_no_recommendation(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write_raw(tmp_path / "odom.bag", "bag", [("/odom", "nav_msgs/msg/Odometry", _odometry, 5)])
    result, err = _inspect(path, capsys)
    assert result["usable"] is False and result["recommendation"] is None and "recommended" not in err
    usable = _log(tmp_path, "bag", (48, 64))
    assert _inspect(usable, capsys)[0]["recommendation"] is not None


@pytest.mark.parametrize("fov", ["0", "-5", "361", "nan", "inf"])
def test_a_field_of_view_out_of_range_exits_2_with_one_line(
    tmp_path: Path, fov: str, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _log(tmp_path, "bag", (48, 64))
    assert main(["inspect", str(path), "--fov", fov]) == 2
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert out == "" and len(lines) == 1 and lines[0].startswith("ERROR: --fov must be")


def test_a_damaged_camera_info_leaves_the_log_usable_and_asks_for_the_field_of_view(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "damaged.bag"
    with Writer1(path) as writer:
        camera = writer.add_connection("/cam/image_raw", "sensor_msgs/msg/Image", typestore=ROS1)
        info = writer.add_connection("/cam/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ROS1)
        for i in range(3):
            stamp = T0_NS + i * 100_000_000
            image = ROS1.serialize_ros1(image_msg(ROS1, stamp, "mono8", (48, 64)), "sensor_msgs/msg/Image")
            writer.write(camera, stamp, image)
            writer.write(info, stamp, b"\x01\x02")  # two bytes: no CameraInfo decodes from them
    result, _err = _inspect(path, capsys)
    assert result["usable"] is True and result["recommendation"]["needs"] == ["fov"]
    # the same log with a sound CameraInfo needs nothing
    sound = _log(tmp_path, "bag", (48, 64), _info(64, 32.0))
    assert _inspect(sound, capsys)[0]["recommendation"]["needs"] == []

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mapserver.cli import main
from tests.mapserver.ingest.conftest import LogFactory, arc_odometry, frame_images, identity_gt


@pytest.fixture
def log_path(make_log: LogFactory) -> Path:
    odometry = arc_odometry(21, 20.0)
    return make_log("mission", "bag", frame_images(11, 10.0, False), odometry, identity_gt(odometry))


def test_inspect_json_last_line(log_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["inspect", str(log_path), "--json"]) == 0
    out, err = capsys.readouterr()
    result = json.loads(out.strip().splitlines()[-1])
    assert {"topics", "mapping", "frames", "duration_s"} <= set(result)
    assert result["frames"] == 11
    assert result["duration_s"] == pytest.approx(1.0, abs=1e-6)
    assert result["mapping"] == {
        "image": "/robot/camera/image",
        "odometry": "/robot/odom",
        "ground_truth": "/robot/ground_truth",
    }
    assert result["odometry_mode"] == "twist"
    for topic in result["topics"]:
        assert {"name", "type", "count", "rate_hz"} <= set(topic)
    assert {t["name"]: t["count"] for t in result["topics"]}["/robot/odom"] == 21
    assert "/robot/camera/image" in err  # the table goes to stderr with --json


def test_inspect_table_and_topics_override(log_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["inspect", str(log_path), "--topics", "odometry=none"]) == 0
    out, _err = capsys.readouterr()
    assert "sensor_msgs/msg/Image" in out and "mapping:" in out
    assert "odometry     -" in out
    assert main(["inspect", str(log_path), "--json", "--topics", "ground_truth=/robot/odom"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["mapping"]["ground_truth"] == "/robot/odom"


@pytest.mark.parametrize(
    "argv",
    [
        ["inspect", "{missing}"],
        ["inspect", "{text}", "--json"],
        ["inspect", "{log}", "--topics", "image"],
        ["inspect", "{log}", "--topics", "depth=/x"],
        ["inspect", "{log}", "--topics", "image=/robot/odom"],
    ],
)
def test_inspect_errors_exit_2_with_one_line(
    argv: list[str], log_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = tmp_path / "text.bag"
    text.write_text("not a bag at all\n")
    paths = {"missing": str(tmp_path / "missing.bag"), "text": str(text), "log": str(log_path)}
    assert main([a.format(**paths) for a in argv]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ERROR: ")

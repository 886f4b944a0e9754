"""``mapserver process --backbone/--weights``: the sdr-htm front-end from the command line, bad input refused."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from core.neocortex.backbones import ShuffleNetV2
from mapserver.cli import main
from mapserver.ingest.writer import write_log
from tests.mapserver.ingest.conftest import arc_odometry, frame_images, identity_gt, test_image


@pytest.fixture
def small_log(tmp_path: Path) -> Path:
    odometry = arc_odometry(31, 10.0, v=0.5, w=0.2)
    images = [(stamp, test_image(i, False, (48, 128))) for i, (stamp, _) in enumerate(frame_images(12, 4.0, False))]
    return write_log(tmp_path / "mission", "mcap", images, odometry, identity_gt(odometry))


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_weights_errors_are_one_line_and_exit_2(small_log: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(capsys, "process", str(small_log), "--preset", "poseidon", "--backbone", "alexnet",
                        "--weights", str(tmp_path / "none.pth"))
    assert code == 2 and "weights file not found" in err and len(err.strip().splitlines()) == 1
    weights = tmp_path / "shufflenet.pth"
    torch.save(ShuffleNetV2().state_dict(), weights)
    code, _, err = _run(capsys, "process", str(small_log), "--preset", "poseidon-lvc", "--backbone", "shufflenetv2",
                        "--weights", str(weights))
    assert code == 2 and "sdr-htm" in err  # LVC preset: the flags do not apply
    code, _, err = _run(capsys, "process", str(small_log), "--preset", "poseidon", "--backbone", "alexnet",
                        "--weights", str(weights))
    assert code == 2 and "do not fit alexnet" in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test_process_with_a_shufflenet_weight_file(small_log: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    weights = tmp_path / "shufflenet.pth"
    torch.save(ShuffleNetV2().state_dict(), weights)
    code, out, err = _run(capsys, "process", str(small_log), "--preset", "poseidon", "--backbone",
                          "shufflenetv2", "--weights", str(weights), "--out", str(tmp_path / "m.json"), "--json")
    assert code == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["frames"] == 12 and 1 <= summary["templates"] <= 12
    doc = json.loads((tmp_path / "m.json").read_text())
    assert doc["params"]["frontend_backbone"] == "shufflenetv2" and doc["params"]["frontend"] == "sdr-htm"

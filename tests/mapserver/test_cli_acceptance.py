"""Issue 3 acceptance, measured with the contract's commands: simulate → process --out → evaluate --json.

* ``loop`` (two laps, ``circle`` preset): at least one loop closure, at least 80 % of the second lap's frames
  recognised from first-lap templates (``revisit_match_rate``), experience-map APE RMSE at most half the raw
  odometry's, and no false matches.
* ``cave3d`` (4-DoF, ``poseidon`` preset): a map whose z follows the ground truth: 3-D APE RMSE and its height
  part at most half the odometry's.

The scenarios are scaled down to keep the suite fast; the full-size figures are in the README.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from mapserver.cli import main

pytestmark = pytest.mark.slow


def _json(capsys: pytest.CaptureFixture[str], *argv: str) -> dict[str, Any]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    assert code == 0, err
    return json.loads(out.strip().splitlines()[-1])


def test_loop_closes_recognises_the_second_lap_and_halves_the_odometry_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "loop"
    scenario = _json(capsys, "simulate", "loop", "--out", str(out), "--seed", "0", "--scale", "0.5", "--json")
    assert scenario["preset"] == "circle"
    log = out / scenario["single"]["log"]
    summary = _json(capsys, "process", str(log), "--out", str(out / "map.json"), "--json")
    result = _json(capsys, "evaluate", str(out / "map.json"), "--ground-truth",
                   str(out / scenario["single"]["ground_truth"]), "--json")
    assert summary["frames"] == scenario["single"]["frames"] > 100
    assert summary["loop_closures"] >= 1
    assert result["revisit_frames"] >= 0.45 * summary["frames"]  # the second lap is a revisit
    assert result["revisit_match_rate"] >= 0.8
    assert result["false_match_rate"] == 0.0
    assert result["ape_rmse"] <= 0.5 * result["odometry_ape_rmse"]
    assert result["odometry_ape_rmse"] > 0.5  # the raw odometry really drifts


def test_cave3d_map_follows_the_ground_truth_in_z(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cave"
    scenario = _json(capsys, "simulate", "cave3d", "--out", str(out), "--seed", "0", "--param",
                     "single_laps=1.5,session1_laps=0.05,session2_laps=0.05", "--json")
    assert scenario["preset"] == "poseidon"
    summary = _json(capsys, "process", str(out / "single.bag"), "--preset", "poseidon",
                    "--out", str(out / "map.json"), "--json")
    result = _json(capsys, "evaluate", str(out / "map.json"), "--ground-truth", str(out / "single.tum"),
                   "--revisit-radius", "0.3", "--match-radius", "0.6", "--false-radius", "1.0", "--json")
    assert summary["loop_closures"] >= 1
    assert result["dims"] == 3
    assert result["ape_rmse"] <= 0.5 * result["odometry_ape_rmse"]
    assert result["ape_z_rmse"] <= 0.5 * result["odometry_ape_z_rmse"]
    assert result["odometry_ape_z_rmse"] > 0.1  # the vertical odometry really drifts
    assert result["false_match_rate"] == 0.0

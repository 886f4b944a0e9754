"""The TUM export read by evo itself: ``evo_ape tum`` agrees with ``mapserver evaluate`` within 1e-6 m.

Alignment: ``evo_ape -a`` (Umeyama, SE(3), no scale) and ``evaluate`` (Umeyama, no scale; planar maps in
xy) solve the same least-squares problem for a planar map (z = 0 in map and ground truth). Association:
evo pairs poses whose stamps differ by at most ``--t_max_diff``; ``evaluate`` interpolates the ground truth
at each experience stamp. The simulator's camera frames fall between its 10 Hz ground-truth samples, so the
reference given to evo is the ground truth interpolated at the experience stamps (written as TUM here);
evo then pairs every experience exactly.
"""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from core.se3 import yaw_from_quaternion
from mapserver.cli import main
from mapserver.evaluation import interpolate_poses
from mapserver.formats import read_tum, write_tum

EVO_APE = Path(sys.executable).with_name("evo_ape")


def _evo_rmse(reference: Path, estimate: Path, out: Path, *rpe: str) -> float:
    """Run ``evo_ape tum REF EST -a`` (or ``evo_rpe tum REF EST RPE...``) and return its RMSE (saved results)."""
    tool = EVO_APE.with_name("evo_rpe") if rpe else EVO_APE
    assert tool.exists(), "evo is a dev dependency: pip install evo"
    options = list(rpe) if rpe else ["-a"]
    command = [str(tool), "tum", str(reference), str(estimate), *options, "--save_results", str(out), "--no_warnings"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    with zipfile.ZipFile(out) as archive:
        return float(json.loads(archive.read("stats.json"))["rmse"])


@pytest.fixture(scope="module")
def loop_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 1.5-lap loop processed into a database and exported as TUM and map JSON (shared by this module)."""
    tmp_path = tmp_path_factory.mktemp("evo")
    sim, db = tmp_path / "sim", f"sqlite:///{tmp_path / 'atlas.db'}"
    argv = ["simulate", "loop", "--out", str(sim), "--seed", "0", "--scale", "0.3", "--param", "laps=1.5"]
    assert main(argv) == 0
    assert main(["process", str(sim / "single.bag"), "--db", db, "--map", "loop"]) == 0
    for fmt in ("tum", "json"):
        assert (
            main(["export", "--db", db, "--map", "loop", "--format", fmt, "--out", str(tmp_path / f"map.{fmt}")]) == 0
        )
    return tmp_path


def _evaluated(folder: Path, capsys: pytest.CaptureFixture[str]) -> dict[str, Any]:
    capsys.readouterr()
    argv = ["evaluate", str(folder / "map.json"), "--ground-truth", str(folder / "sim" / "single.tum"), "--json"]
    assert main(argv) == 0
    result: dict[str, Any] = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    return result


@pytest.mark.slow
def test_evo_ape_on_the_tum_export_agrees_with_evaluate(
    loop_map: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sim = loop_map / "sim"
    evaluated = _evaluated(loop_map, capsys)

    estimate = read_tum(loop_map / "map.tum")
    truth = interpolate_poses(read_tum(sim / "single.tum"), estimate.stamps_s)
    assert not np.isnan(truth).any() and estimate.stamps_s.shape[0] == evaluated["aligned"] > 10
    reference = tmp_path / "truth_at_experiences.tum"
    write_tum(reference, estimate.stamps_s, truth, np.tile([0.0, 0.0, 0.0, 1.0], (truth.shape[0], 1)))
    rmse = _evo_rmse(reference, loop_map / "map.tum", tmp_path / "ape.zip")
    assert evaluated["ape_rmse"] > 0.01  # a real error, not a trivially aligned map
    assert abs(rmse - evaluated["ape_rmse"]) < 1e-6

    # must still differ: evo on a map whose poses were moved by 0.5 m reports a different error
    moved = read_tum(loop_map / "map.tum")
    positions = moved.positions_xyz.copy()
    positions[0, 0] += 0.5
    write_tum(tmp_path / "moved.tum", moved.stamps_s, positions, moved.quat_xyzw)
    assert abs(_evo_rmse(reference, tmp_path / "moved.tum", tmp_path / "moved.zip") - rmse) > 1e-3


@pytest.mark.slow
def test_evo_rpe_agrees_with_evaluate_over_1_m_and_10_m(
    loop_map: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``evaluate``'s RPE (translation and rotation) is ``evo_rpe --pairs_from_reference``'s within 1e-6.

    The reference given to evo is the ground truth at the experience stamps: positions interpolated
    linearly, yaw interpolated along its unwrapped angle (the test's own interpolation).
    """
    evaluated = _evaluated(loop_map, capsys)
    estimate = read_tum(loop_map / "map.tum")
    truth = read_tum(loop_map / "sim" / "single.tum").sorted()
    positions = interpolate_poses(truth, estimate.stamps_s)
    yaw = np.unwrap([yaw_from_quaternion(*q) for q in truth.quat_xyzw])
    at = np.interp(estimate.stamps_s, truth.stamps_s, yaw)
    quats = np.column_stack([np.zeros(at.size), np.zeros(at.size), np.sin(at / 2), np.cos(at / 2)])
    reference = tmp_path / "truth.tum"
    write_tum(reference, estimate.stamps_s, positions, quats)
    for entry in evaluated["rpe"]:
        delta = ["--delta", f"{entry['delta_m']:g}", "--delta_unit", "m", "--pairs_from_reference"]
        trans = _evo_rmse(reference, loop_map / "map.tum", tmp_path / "t.zip", *delta, "--pose_relation", "trans_part")
        rot = _evo_rmse(reference, loop_map / "map.tum", tmp_path / "r.zip", *delta, "--pose_relation", "angle_deg")
        assert entry["pairs"] >= (3 if entry["delta_m"] < 10 else 1) and entry["trans_rmse"] > 1e-3  # real drift
        assert abs(trans - entry["trans_rmse"]) < 1e-6
        assert abs(rot - entry["rot_rmse_deg"]) < 1e-6

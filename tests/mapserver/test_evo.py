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
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from mapserver.cli import main
from mapserver.evaluation import interpolate_poses
from mapserver.formats import read_tum, write_tum

EVO_APE = Path(sys.executable).with_name("evo_ape")


def _evo_rmse(reference: Path, estimate: Path, out: Path) -> float:
    """Run ``evo_ape tum REF EST -a`` and return its RMSE (from its saved results)."""
    assert EVO_APE.exists() or shutil.which("evo_ape"), "evo is a dev dependency: pip install evo"
    command = [str(EVO_APE if EVO_APE.exists() else "evo_ape"), "tum", str(reference), str(estimate), "-a",
               "--save_results", str(out), "--no_warnings"]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    with zipfile.ZipFile(out) as archive:
        return float(json.loads(archive.read("stats.json"))["rmse"])


@pytest.mark.slow
def test_evo_ape_on_the_tum_export_agrees_with_evaluate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sim, db = tmp_path / "sim", f"sqlite:///{tmp_path / 'atlas.db'}"
    argv = ["simulate", "loop", "--out", str(sim), "--seed", "0", "--scale", "0.3", "--param", "laps=1.5"]
    assert main(argv) == 0
    assert main(["process", str(sim / "single.bag"), "--db", db, "--map", "loop"]) == 0
    for fmt in ("tum", "json"):
        assert (
            main(["export", "--db", db, "--map", "loop", "--format", fmt, "--out", str(tmp_path / f"map.{fmt}")]) == 0
        )
    capsys.readouterr()
    assert main(["evaluate", str(tmp_path / "map.json"), "--ground-truth", str(sim / "single.tum"), "--json"]) == 0
    evaluated = json.loads(capsys.readouterr().out.strip().splitlines()[-1])

    estimate = read_tum(tmp_path / "map.tum")
    truth = interpolate_poses(read_tum(sim / "single.tum"), estimate.stamps_s)
    assert not np.isnan(truth).any() and estimate.stamps_s.shape[0] == evaluated["aligned"] > 10
    reference = tmp_path / "truth_at_experiences.tum"
    write_tum(reference, estimate.stamps_s, truth, np.tile([0.0, 0.0, 0.0, 1.0], (truth.shape[0], 1)))
    rmse = _evo_rmse(reference, tmp_path / "map.tum", tmp_path / "ape.zip")
    assert evaluated["ape_rmse"] > 0.01  # a real error, not a trivially aligned map
    assert abs(rmse - evaluated["ape_rmse"]) < 1e-6

    # must still differ: evo on a map whose poses were moved by 0.5 m reports a different error
    moved = read_tum(tmp_path / "map.tum")
    positions = moved.positions_xyz.copy()
    positions[0, 0] += 0.5
    write_tum(tmp_path / "moved.tum", moved.stamps_s, positions, moved.quat_xyzw)
    assert abs(_evo_rmse(reference, tmp_path / "moved.tum", tmp_path / "moved.zip") - rmse) > 1e-3

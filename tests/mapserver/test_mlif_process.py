"""``pc_model = mlif`` through ``mapserver process``: a simulated loop mapped by the spiking pose cells.

Figures on this log (``loop``, seed 1, scale 0.5, 139 frames), measured: APE 0.178 m (odometry 0.859 m), one loop
closure; the CAN pose cells on the same log: see ``bench/mlif.py`` for the comparison over seeds.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mapserver.cli import main
from tests.simulations import simulate_once


@pytest.fixture(scope="module")
def loop_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("mlif-loop")
    simulate_once("loop", folder, seed=1, scale=0.5)
    return folder


def test_mlif_maps_the_loop_closes_it_and_beats_odometry(loop_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = loop_log / "mlif.json"
    assert main(["process", str(loop_log / "single.bag"), "--preset", "circle", "--set", "pc_model=mlif",
                 "--out", str(out)]) == 0
    assert main(["evaluate", str(out), "--ground-truth", str(loop_log / "single.tum"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    data = json.loads(out.read_text())
    assert data["params"]["pc_model"] == "mlif"
    assert [link["kind"] for link in data["links"]].count("loop") >= 1
    assert report["ape_rmse"] < 0.5 * report["odometry_ape_rmse"]
    again = loop_log / "mlif-again.json"
    assert main(["process", str(loop_log / "single.bag"), "--preset", "circle", "--set", "pc_model=mlif",
                 "--out", str(again)]) == 0
    assert again.read_bytes() == out.read_bytes()  # the same log gives the same map, bit for bit


def test_an_mlif_map_is_refused_by_the_store_before_any_work(loop_log: Path, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    from core import preset
    from core.config import ConfigError
    from mapserver.params import require_storable

    db = tmp_path / "maps.sqlite"
    code = main(["process", str(loop_log / "single.bag"), "--preset", "circle", "--set", "pc_model=mlif",
                 "--db", f"sqlite:///{db}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err == ["ERROR: maps of the mlif pose cells cannot be stored in a database yet: process with --out MAP.json"]
    assert not db.exists()  # refused before the database was opened
    with pytest.raises(ConfigError, match="mlif pose cells cannot be stored"):
        require_storable(preset("circle").replace(pc_model="mlif"))
    assert require_storable(preset("circle")).pc_model == "can"  # the CAN pose cells still store

"""``engine = neuroslam`` through ``mapserver process``: a simulated loop, mapped and evaluated.

Figures on this log (seed 1, scale 0.5, 2 laps): see the assertions; they are measured, with margins.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mapserver.cli import main
from tests.simulations import simulate_once


@pytest.fixture(scope="module")
def loop_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("neuroslam-loop")
    simulate_once("loop", folder, seed=1, scale=0.5)
    return folder


def process(folder: Path, name: str, *options: str) -> None:
    out = folder / f"{name}.json"
    assert main(["process", str(folder / "single.bag"), "--out", str(out), *options]) == 0
    assert main(["evaluate", str(out), "--ground-truth", str(folder / "single.tum"), "--json"]) == 0


def test_the_neuroslam_preset_closes_loops_and_beats_odometry(
    loop_log: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    process(loop_log, "neuro", "--preset", "neuroslam")
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    data = json.loads((loop_log / "neuro.json").read_text())
    assert data["params"]["engine"] == "neuroslam"
    kinds = [link["kind"] for link in data["links"]]
    assert kinds.count("loop") >= 3
    # one experience per template, as the paper's §6.1.3 reports: between two templates the codes never move S_max
    assert len(data["experiences"]) == data["templates"]
    assert report["ape_rmse"] < 0.5 * report["odometry_ape_rmse"]


def test_the_same_log_gives_the_same_map(loop_log: Path) -> None:
    process(loop_log, "a", "--preset", "neuroslam")
    process(loop_log, "b", "--preset", "neuroslam")
    assert (loop_log / "a.json").read_bytes() == (loop_log / "b.json").read_bytes()


def test_a_neuroslam_map_is_refused_by_the_store_before_any_work(loop_log: Path, tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    from core.config import ConfigError
    from mapserver.api.intake import parse_options

    db = tmp_path / "maps.sqlite"
    code = main(["process", str(loop_log / "single.bag"), "--preset", "neuroslam", "--db", f"sqlite:///{db}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    refusal = "maps of the neuroslam engine cannot be stored in a database yet: process with --out MAP.json"
    assert err == [f"ERROR: {refusal}"]
    assert not db.exists()  # refused before the database was opened
    with pytest.raises(ConfigError, match="neuroslam engine cannot be stored"):
        parse_options({"preset": "neuroslam"})  # an upload: 400 before 202
    assert parse_options({"preset": "circle"}).preset == "circle"  # the store's own engine still uploads

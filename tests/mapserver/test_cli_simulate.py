"""``mapserver simulate`` end to end: contract JSON, files, parameters and errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mapserver.cli import main
from mapserver.cli.simulate import parse_params
from mapserver.errors import InputError


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_simulate_json_is_scenario_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out_dir = tmp_path / "ell"
    code, out, err = _run(
        capsys, "simulate", "ellipse", "--out", str(out_dir), "--seed", "2", "--format", "db3",
        "--scale", "0.25", "--param", "session2_laps=0.5,single_laps=0.3", "--param", "heading_offset_deg=90", "--json",
    )
    assert code == 0
    result = json.loads(out.strip().splitlines()[-1])
    assert result == json.loads((out_dir / "scenario.json").read_text())
    assert result["scenario"] == "ellipse" and result["preset"] == "circle"
    assert [s["name"] for s in result["sessions"]] == ["session1", "session2"]
    for entry in [*result["sessions"], result["single"]]:
        assert (out_dir / entry["log"]).is_file() and entry["log"].endswith(".db3")
        assert (out_dir / entry["ground_truth"]).is_file()
    assert result["sessions"][1]["turn_deg"] == 90.0
    assert result["params"]["session2_laps"] == 0.5
    assert "preset: circle" in err


def test_process_picks_the_preset_named_in_scenario_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out_dir = tmp_path / "cave"
    assert _run(capsys, "simulate", "cave3d", "--out", str(out_dir), "--param",
                "single_laps=0.1,session1_laps=0.05,session2_laps=0.05")[0] == 0
    code, _, _ = _run(capsys, "process", str(out_dir / "single.bag"), "--out", str(tmp_path / "m.json"), "--json")
    assert code == 0
    assert json.loads((tmp_path / "m.json").read_text())["params"]["pc_dim_z"] == 15  # poseidon's 4-DoF lattice


@pytest.mark.parametrize(
    ("argv", "reason"),
    [
        (
            ["moon"],
            "unknown scenario 'moon' (valid: loop, figure8, ellipse, bridge, chain5, cave3d, aliased, "
            "twin, twin-overlap, symmetric, symmetric-overlap, street, building, terrain, seabed)",
        ),
        (["loop", "--param", "laps"], "expected NAME=VALUE"),
        (["loop", "--param", "laps=two"], "not a finite number"),
        (["loop", "--param", "speed=2"], "unknown parameter 'speed' for scenario 'loop'"),
        (["loop", "--format", "rosbag"], "unknown log format 'rosbag'"),
        (["loop", "--scale", "-1"], "scale must be a positive number"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], reason: str
) -> None:
    out_dir = tmp_path / "out"
    code, out, err = _run(capsys, "simulate", *argv, "--out", str(out_dir))
    assert code == 2 and out == ""
    lines = [line for line in err.splitlines() if line.startswith("ERROR:")]
    assert len(lines) == 1 and reason in lines[0]
    assert not out_dir.exists()
    assert list(tmp_path.iterdir()) == []


def test_parse_params() -> None:
    assert parse_params(["a=1,b=2.5", " c = -3 "]) == {"a": 1.0, "b": 2.5, "c": -3.0}
    with pytest.raises(InputError, match="given twice"):
        parse_params(["a=1", "a=2"])
    with pytest.raises(InputError, match="finite"):
        parse_params(["a=inf"])

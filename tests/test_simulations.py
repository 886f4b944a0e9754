"""The run's shared simulations (tests/simulations.py): rendered once, copied as the simulator writes them."""

from __future__ import annotations

from pathlib import Path

import pytest

import tests.simulations as simulations
from mapserver.ingest.simulator import simulate


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def test_a_scenario_is_rendered_once_and_each_caller_gets_the_simulators_files(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(simulations.CACHE_ENV, str(tmp_path / "shared"))
    (tmp_path / "shared").mkdir()
    calls: list[str] = []

    def counted(scenario: str, out_dir: Path, **kw: object) -> dict:
        calls.append(scenario)
        return simulate(scenario, out_dir, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(simulations, "simulate", counted)
    args = {"seed": 5, "scale": 0.3, "params": {"laps": 0.3}}
    first = simulations.simulate_once("loop", tmp_path / "a", **args)  # type: ignore[arg-type]
    second = simulations.simulate_once("loop", tmp_path / "b", **args)  # type: ignore[arg-type]
    other = simulations.simulate_once("loop", tmp_path / "c", **{**args, "seed": 6})  # type: ignore[arg-type]
    assert calls == ["loop", "loop"]  # the same arguments once, another seed again
    direct = simulate("loop", tmp_path / "direct", **args)  # type: ignore[arg-type]
    assert first == second == direct and other["seed"] == 6
    assert _files(tmp_path / "a") == _files(tmp_path / "b") == _files(tmp_path / "direct")
    assert _files(tmp_path / "c") != _files(tmp_path / "a")

"""NeuroSLAM's building bench (bench/neuroslam_building.py): its floor-collapse counter, and a small run."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import neuroslam_building as bench

pytestmark = pytest.mark.slow

FLOORS = bench.Floors(z_m=(0.0, 3.0), storey_m=3.0)


def _doc(links: list[tuple[int, int, str]]) -> dict:
    return {"links": [{"from": a, "to": b, "kind": k} for a, b, k in links]}


def test_a_link_between_storeys_away_from_the_ramp_is_wrong() -> None:
    truth = {
        0: [5.0, 5.0, 0.0],
        1: [5.2, 5.0, 3.0],
        2: [-5.0, 5.0, 0.02],
        3: [0.0, -5.0, 0.0],
        4: [0.1, -5.0, 3.0],
        5: [0.7, -5.2, 0.14],  # the foot of the ramp
    }
    links = [(1, 0, "loop"), (0, 2, "loop"), (3, 4, "odometry"), (4, 5, "loop")]
    assert bench.wrong_links(_doc(links), truth, FLOORS) == [
        {"from": 1, "to": 0, "kind": "loop", "z": [3.0, 0.0]},  # the same spot one storey up
        {"from": 3, "to": 4, "kind": "odometry", "z": [0.0, 3.0]},  # the landings below and above the ramp
        {"from": 4, "to": 5, "kind": "loop", "z": [3.0, 0.14]},  # a closure from the landing to the ramp's foot
    ]


def test_links_on_one_storey_or_up_the_ramp_are_not_wrong() -> None:
    truth = {
        0: [5.0, 5.0, 0.0],
        1: [6.0, 5.0, 0.04],  # one storey
        2: [0.0, -5.0, 0.0],  # the landing below
        3: [0.0, -10.0, 1.5],  # half-way up the ramp
        4: [0.0, -5.0, 3.0],  # the landing above
        5: [0.5, -5.1, 0.06],  # the foot of the ramp, 6 cm up
        6: [8.0, 0.0, 3.0],
    }
    links = [(0, 1, "loop"), (2, 3, "odometry"), (3, 4, "odometry"), (5, 6, "odometry"), (0, 9, "loop")]
    assert bench.wrong_links(_doc(links), truth, FLOORS) == []


def test_recognised_views_are_counted_by_the_storey_that_made_them(tmp_path: Path) -> None:
    gt = tmp_path / "gt.tum"
    gt.write_text("0 5 5 0 0 0 0 1\n10 5 5 0 0 0 0 1\n10.1 5 5 3 0 0 0 1\n20 5 5 3 0 0 0 1\n")
    frames = [[1.0, 0, 1], [2.0, 1, 1], [3.0, 0, 0], [15.0, 0, 0], [16.0, 2, 1], [17.0, 2, 0]]
    counts = bench.cross_floor_views({"frames": frames}, gt, FLOORS)
    assert counts == {"frames": 3, "other_floor": 1}  # frame 3 (storey 1's template 0 seen on storey 2)


def test_the_bench_runs_small_and_prints_its_json_line(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    assert bench.main(["--seeds", "1", "--small", "--work", str(tmp_path)]) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out.strip().splitlines()[-1])
    assert summary["small"] and summary["seeds"] == [0, 0]
    assert set(summary["engines"]) == {"neuroslam", "poseidon-lvc", "circle"}
    runs = {r["engine"]: r for r in summary["runs"]}
    for engine, row in runs.items():
        assert 0.0 < row["ape_rmse"] < 5.0 and row["dims"] == 3, engine
        assert row["collapsed"] == (row["wrong_links"] > 0), engine
        stats = summary["engines"][engine]
        assert stats["collapsed_seeds"] == int(row["collapsed"]) and stats["ape_rmse"]["median"] == pytest.approx(
            row["ape_rmse"], abs=1e-4
        )
    assert "seed 0 neuroslam" in captured.err
    assert (tmp_path / "small-0" / "single.bag").exists()  # the log is kept and reused
    # The storeys look alike: the 3-DoF map links them. NeuroSLAM's preset keeps them apart (S_max 10 cells, the
    # storeys 12 + 12 height cells apart); the paper's S_max of 40 cells with metre cells (the whole code space)
    # never refuses a view's link, and links them (docs/journal.md, "NeuroSLAM keeps the storeys apart").
    assert runs["circle"]["collapsed"] and not runs["neuroslam"]["collapsed"]
    assert runs["neuroslam"]["experiences"] > 0
    paper = bench.run_engine_on(tmp_path / "small-0", "neuroslam", {
        "exp_delta_pc_threshold": 40.0, "gc_cell_size_z": 1.0, "hdc_cell_size_height": 1.0})
    assert paper["wrong_links"] > 0

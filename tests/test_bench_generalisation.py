"""The generalisation bench (bench/generalisation.py) run small: its draws, its table and its JSON line."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import generalisation

pytestmark = pytest.mark.slow


def test_every_seed_draws_its_own_vehicle_within_the_documented_ranges() -> None:
    draws = [generalisation.draw(family, seed) for family in ("street", "dusk") for seed in range(12)]
    sensors = [d.sensors for d in draws]
    for name, lo, hi in (("fov_deg", 40, 90), ("camera_hz", 5, 15), ("odom_hz", 10, 50), ("speed", 0.3, 2.0),
                         ("jpeg_quality", 60, 95), ("scale_error", 0.01, 0.05), ("yaw_bias", 0.002, 0.012)):
        values = np.array([getattr(s, name) for s in sensors])
        assert values.min() >= lo and values.max() <= hi, name
        assert len(np.unique(values)) > 8, name  # drawn per seed, not shared
    street = [d for d in draws if d.family == "street"]
    dusk = [d for d in draws if d.family == "dusk"]
    assert all(d.sensors.light_turn_deg == 0.0 and d.sensors.light_gain == 0.0 for d in street)
    assert all(30 <= d.sensors.light_turn_deg <= 90 and -0.35 <= d.sensors.light_gain <= -0.15 for d in dusk)
    assert generalisation.draw("street", 3) == generalisation.draw("street", 3)  # the same seed, the same draw


def test_the_bench_runs_small_and_prints_its_table_and_json_line(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    argv = ["--seeds", "1", "--families", "campus,street", "--small", "--jobs", "1", "--work", str(tmp_path),
            "--variant", "joint:exp_relax_joint=1"]  # fmt: skip
    assert generalisation.main(argv) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out.strip().splitlines()[-1])
    assert summary["runs"] == 2 and set(summary["families"]) == {"campus", "street"}
    for stats in summary["families"].values():
        for mode in ("default", "default_unsettled", "joint"):
            assert stats[mode]["n"] == 1 and 0.0 < stats[mode]["median"] == stats[mode]["p90"] < 50.0
        assert stats["compat_ape_median"] > 0.0
    assert "ratio to compat" in captured.err and "campus" in captured.err
    # a second run reads every mode from the cache beside each log
    assert all((tmp_path / f"{f}-00" / "results.json").exists() for f in ("campus", "street"))

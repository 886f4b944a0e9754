"""A new user follows the README's "Your own bag" on a forward-camera log and gets a map as good as the bench's.

The section's shell block runs as written (simulate → inspect → process with the INI inspect wrote → evaluate),
in a fresh directory, with ``mapserver`` on ``PATH`` (:mod:`tests.test_readme`'s shim). The map's APE must be
within the generalisation bench's median for the ``street`` family on logs of this size: 0.35 m, the median of
``python bench/generalisation.py --small --families street --seeds 6`` (the bench's small logs: 1.2 laps of an
8 m deep block at ≥ 1 m/s, ≤ 5 frames/s; seeds 0–5: 0.50, 0.19, 0.63, 0.18, 0.68, 0.21 m; docs/journal.md,
"Your own bag"). On its full-size logs the bench's street median is 0.55 m (docs/engine.md).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from core import load_config, preset
from tests.test_readme import README, ROOT, _shim, shell_blocks

sys.path.insert(0, str(ROOT / "bench"))

import generalisation

pytestmark = pytest.mark.slow

BENCH_SMALL_STREET_MEDIAN_APE_M = 0.35
SECTION = "## Your own bag"


def _section_block() -> str:
    """Return the one shell block of the README's "Your own bag" section."""
    text = README.read_text(encoding="utf-8")
    start = text.index(SECTION)
    end = text.find("\n## ", start + len(SECTION))
    blocks = shell_blocks(text[start : end if end > 0 else len(text)])
    assert [b.kind for b in blocks] == ["run"], "the section holds one shell block, run by the tests"
    return blocks[0].code


def _json_lines(stdout: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in stdout.splitlines() if line.startswith("{")]


def test_the_sections_log_is_one_of_the_benchs_small_street_logs() -> None:
    # the bench's --small street draws: 1.2 laps, an 8 m deep block 1.2-2.5 times as wide, camera at 5 Hz
    # (min of 5-15), 1-2 m/s; the simulator's other defaults (75° camera, 20 Hz odometry, JPEG 80, 2.5 % scale
    # error, 0.004 rad/s yaw bias) lie inside the bench's ranges (40-90°, 10-50 Hz, 60-95, 1-5 %, 0.002-0.012)
    simulate = next(line for line in _section_block().splitlines() if line.startswith("mapserver simulate street"))
    params = dict(pair.split("=") for pair in re.search(r"--param (\S+)", simulate).group(1).split(","))  # type: ignore[union-attr]
    values = {key: float(value) for key, value in params.items()}
    assert values["laps"] == 1.2 and values["block_h_m"] == 8.0 and values["camera_hz"] == 5.0
    assert 1.2 <= values["block_w_m"] / values["block_h_m"] <= 2.5 and 1.0 <= values["speed"] <= 2.0
    small = generalisation.draw("street", 0, small=True)
    assert (small.params["laps"], small.params["block_h_m"], small.sensors.camera_hz) == (1.2, 8.0, 5.0)
    # what the bench runs as "default" is the forward preset with the log's own field of view
    assert generalisation.ini_params(small, {}) == preset("forward").replace(camera_fov_deg=small.sensors.fov_deg)


def test_following_the_section_gives_a_map_within_the_benchs_median(tmp_path: Path) -> None:
    _shim(tmp_path / "bin")
    env = {
        **os.environ,
        "PATH": os.pathsep.join([str(tmp_path / "bin"), os.environ.get("PATH", "")]),
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    work = tmp_path / "work"
    work.mkdir()
    code = _section_block()
    done = subprocess.run(["bash", "-eu", "-c", code], cwd=work, env=env, capture_output=True, text=True,
                          timeout=300, check=False)  # fmt: skip
    assert done.returncode == 0, f"{code}\n--- stdout\n{done.stdout[-3000:]}\n--- stderr\n{done.stderr[-3000:]}"
    # inspect recommended forward with the field of view given and the log's 5 Hz camera, and wrote it as the INI
    assert "recommended: preset forward" in done.stdout
    ini = next(work.glob("*.ini"))
    assert load_config(ini) == preset("forward").replace(camera_fov_deg=75.0, camera_hz=5.0)
    summary = next(line for line in _json_lines(done.stdout) if "loop_closures" in line)
    evaluation = next(line for line in _json_lines(done.stdout) if "ape_rmse" in line)
    # the map closed the block's loop and corrected the odometry's drift ...
    assert summary["loop_closures"] >= 1 and summary["templates"] < summary["frames"]
    assert evaluation["ape_rmse"] < evaluation["odometry_ape_rmse"]
    assert evaluation["false_match_rate"] == 0.0
    # ... as well as the bench's median map of the family
    assert evaluation["ape_rmse"] <= BENCH_SMALL_STREET_MEDIAN_APE_M
    # the other form inspect printed, 'process LOG --preset forward --set ...', makes the same map as the INI
    printed = next(line.strip() for line in done.stdout.splitlines() if line.strip().startswith("mapserver process"))
    assert "--preset forward --set camera_fov_deg=75,camera_hz=5," in printed
    again = subprocess.run(["bash", "-eu", "-c", f"{printed} --out set.json"], cwd=work, env=env, capture_output=True,
                           text=True, timeout=300, check=False)  # fmt: skip
    assert again.returncode == 0, again.stderr[-3000:]
    by_ini, by_set = (json.loads(next(work.glob(name)).read_text()) for name in ("mybag.json", "set.json"))
    assert by_set["experiences"] == by_ini["experiences"] and by_set["links"] == by_ini["links"]

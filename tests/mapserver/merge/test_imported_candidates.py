"""Issue 12 part 5: a map imported from another tool's save is a merge candidate like a map we built.

Session 1 of a scenario is mapped without a database, written in multisession-ratslam's save format
(:func:`write_msr_save`, the layout ``mapserver.store.import_msr`` reads), imported with ``mapserver
import``, and session 2 is processed against it. The import loses what that format lacks (stamps rebuilt
from link Δt, link kinds guessed, pose-cell activity reset), so these tests check that the merge decision,
its probation and the offline merge work on such a map: the true overlap (``twin-overlap``) merges, online
and offline, at its true place; the look-alike of another place (``twin``) never survives.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from core import preset
from mapserver.cli import main
from mapserver.processing.pipeline import process_log
from mapserver.store import load_map, open_database
from tests.mapserver.merge.scenario_metrics import cli_json, true_alignment
from tests.simulations import simulate_once

pytestmark = pytest.mark.slow


def _numbers(values: Any) -> str:
    return "".join(f"{float(v):.18e} " for v in np.ravel(values))


def write_msr_save(directory: Path, state: dict[str, np.ndarray]) -> Path:
    """Write a 3-DoF engine snapshot as a multisession-ratslam save directory (its five text files)."""
    directory.mkdir(parents=True, exist_ok=True)
    templates, means = state["lv_templates"], state["lv_means"]
    lvc = [str(templates[0].size)]
    for k in range(templates.shape[0]):
        lvc += [str(k), repr(float(means[k])), _numbers(templates[k])]
    lvc += ["-", str(int(state["lv_current"])), str(int(state["lv_previous"]))]
    (directory / "localviewcells.txt").write_text("\n".join(lvc) + "\n")
    pose, template, pc = state["em_pose"], state["em_template"], state["em_pc"]
    pcvt: list[str] = []
    for k, (t, coords, decay) in enumerate(zip(state["pc_link_template"], state["pc_link_coords"],
                                               state["pc_link_decay"], strict=True)):  # fmt: skip
        assert int(t) == k, "one pose-cell link per template, in template order (as OpenRatSLAM)"
        pcvt += [str(k), *(repr(float(c)) for c in coords), repr(float(decay)), _numbers(np.flatnonzero(template == k))]
    pcvt += ["-", str(int(state["pc_current_vt"])), str(int(state["pc_prev_vt"]))]
    (directory / "posecellvisual_templates.txt").write_text("\n".join(pcvt) + "\n")
    pcexp = [line for i in range(pose.shape[0]) for line in (*(repr(float(c)) for c in pc[i]), str(int(template[i])))]
    pcexp += ["-", str(int(state["em_current"])), str(int(state["em_previous"]))]
    (directory / "posecellexperiences.txt").write_text("\n".join(pcexp) + "\n")
    src, dst, transform = state["em_link_from"], state["em_link_to"], state["em_link_transform"]
    exps: list[str] = []
    for i in range(pose.shape[0]):
        exps += [str(i), repr(float(pose[i, 0])), repr(float(pose[i, 1])), repr(float(pose[i, 3])),
                 str(int(template[i])), _numbers(np.flatnonzero(src == i)), _numbers(np.flatnonzero(dst == i)),
                 "0", "-1", "-1"]  # fmt: skip
    exps += ["-", str(int(state["em_current"])), str(int(state["em_previous"]))]
    (directory / "experiences.txt").write_text("\n".join(exps) + "\n")
    links: list[str] = []
    for a, b, t, dt in zip(src, dst, transform, state["em_link_dt"], strict=True):
        d, heading = math.hypot(t[0], t[1]), math.atan2(t[1], t[0])
        links += [repr(d), repr(heading), repr(float(t[3])), str(int(b)), str(int(a)), repr(float(dt))]
    (directory / "links.txt").write_text("\n".join(links) + "\n")
    (directory / "goal_list.txt").write_text("")
    return directory


def _imported_atlas(tmp_path: Path, name: str) -> tuple[Path, dict[str, Any], str]:
    """Simulate ``name`` (seed 0), map session 1 alone, write it as a save, import it as map ``tool``."""
    directory = tmp_path / name
    info = simulate_once(name, directory, seed=0, only=("session1", "session2"))
    params = preset(info["preset"])
    mapped = process_log(directory / info["sessions"][0]["log"], params)
    save = write_msr_save(tmp_path / f"{name}-save", mapped.engine.snapshot())
    db = f"sqlite:///{tmp_path / f'{name}.db'}"
    imported = cli_json("import", str(save), "--format", "multisession-ratslam", "--map", "tool", "--preset",
                        info["preset"], "--db", db)  # fmt: skip
    assert imported["experiences"] == mapped.engine.map.count
    return directory, info, db


def test_a_session_merges_into_an_imported_map_at_its_true_place_online_and_offline(tmp_path: Path) -> None:
    directory, info, db = _imported_atlas(tmp_path, "twin-overlap")
    s1, s2 = info["sessions"][:2]
    truth = true_alignment(directory, s1, s2, math.radians(preset(info["preset"]).exp_initial_em_deg))
    result = cli_json("process", str(directory / s2["log"]), "--db", db)
    applied = [m for m in result["merges"] if m["status"] == "applied"]
    assert [m["into"] for m in applied] == ["tool"]
    assert applied[0]["evidence"]["verification"]["status"] == "passed"
    t = applied[0]["transform"]
    assert math.hypot(t["x"] - truth[0], t["y"] - truth[1]) < 5.0
    assert abs(math.remainder(t["yaw"] - truth[3], math.tau)) < 0.35
    (listed,) = cli_json("maps", "--db", db)["maps"]
    assert (listed["name"], listed["sessions"], listed["merges"]["applied"]) == ("tool", 2, 1)

    offline_db = f"sqlite:///{tmp_path / 'offline.db'}"
    save = tmp_path / "twin-overlap-save"
    cli_json("import", str(save), "--format", "multisession-ratslam", "--map", "tool", "--preset", info["preset"],
             "--db", offline_db)  # fmt: skip
    cli_json("process", str(directory / s2["log"]), "--db", offline_db, "--no-merge")
    with open_database(offline_db) as opened:
        saved = load_map(opened, name="tool").snapshot["em_pose"]
    merged = cli_json("merge", "--db", offline_db, "--map", "session2", "--into", "tool")
    assert (merged["map"], merged["settled"]) == ("tool", False)  # the tool's poses are kept: nothing settles
    (listed,) = cli_json("maps", "--db", offline_db)["maps"]
    assert (listed["name"], listed["sessions"]) == ("tool", 2)
    with open_database(offline_db) as opened:
        kept = load_map(opened, name="tool").snapshot["em_pose"][: saved.shape[0]]
    np.testing.assert_array_equal(kept, saved)
    # asked to settle, the same merge moves the imported experiences to the merged graph's fixed point
    assert main(["unmerge", "--db", offline_db, "--event", str(merged["event"])]) == 0
    settled = cli_json("merge", "--db", offline_db, "--map", "session2", "--into", "tool", "--settle")
    assert settled["settled"] is True
    with open_database(offline_db) as opened:
        moved = load_map(opened, name="tool").snapshot["em_pose"][: saved.shape[0]]
    assert np.abs(moved - saved).max() > 1e-3


def test_a_look_alike_of_another_place_never_merges_into_an_imported_map(tmp_path: Path) -> None:
    directory, info, db = _imported_atlas(tmp_path, "twin")
    result = cli_json("process", str(directory / info["sessions"][1]["log"]), "--db", db)
    assert [m for m in result["merges"] if m["status"] == "applied"] == []
    names = sorted(m["name"] for m in cli_json("maps", "--db", db)["maps"])
    assert names == ["session2", "tool"]

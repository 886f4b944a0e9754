"""Issue 5 acceptance through the database with the contract's commands (simulate, process --db, maps, path, ...).

* ellipse (Menezes et al.'s Virtual Tour): one merge; after it ≤ 5 % of session 2's frames on session 1's
  path create experiences; experience count within 10 % of the single-session run; ICP RMSE between the
  merged and the single-session map ≤ 5 % of its extent. Without operation (iii) the partial map's own
  ground is mapped anew (Fig. 12); a session 2 starting 90° turned meets the same bounds.
* bridge: one map, two merge events, a path from the first region to the second; chain5: one connected map.
* cave3d (4-DoF): one merge, merged depths as accurate as the single-session map's.
* aliased: no false merge with the default K, the false merge with K = 1.

The ellipse runs at full scale: at half scale the 90° session's in-place turn (5 frames of experiences at
new headings, legitimate) is already 10 % of the map, so the bound would measure the turn, not the merge.
The other scenarios run at the simulator's scale too (they are small). Full figures: README.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from core import preset
from core import robust as robust_module
from mapserver.merge import online as online_module
from mapserver.merge import verify as verify_module
from mapserver.store import open_database
from mapserver.store.merge_events import list_merge_events
from tests.mapserver.merge.scenario_metrics import (
    cli_code,
    cli_json,
    experiences,
    load_doc,
    measure_ellipse,
    true_alignment,
)
from tests.simulations import simulate_once

pytestmark = pytest.mark.slow

SESSIONS = ("session1", "session2")  # the logs a test of two sessions needs (not the single route's)


@pytest.fixture(scope="session")
def scenario(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """``scenario(name, param=value...)`` → (directory, scenario.json), simulated once per worker."""
    cache: dict[tuple[str, str], tuple[Path, dict[str, Any]]] = {}

    def get(name: str, **params: float) -> tuple[Path, dict[str, Any]]:
        key = (name, json.dumps(params, sort_keys=True))
        if key not in cache:
            directory = tmp_path_factory.mktemp(name)
            cache[key] = (directory, simulate_once(name, directory, seed=0, params=params))
        return cache[key]

    return get


@pytest.fixture(scope="session")
def ellipse_single(scenario: Any) -> dict[str, Any]:
    """The single-session map of the ellipse (2.5 laps, no database)."""
    directory, info = scenario("ellipse")
    out = directory / "single-map.json"
    cli_json("process", str(directory / info["single"]["log"]), "--out", str(out))
    return load_doc(out)


def _db(tmp_path: Path, name: str = "atlas") -> str:
    return f"sqlite:///{tmp_path / f'{name}.db'}"


def test_ellipse_merges_once_and_the_lattice_shift_is_what_prevents_new_experiences(
    scenario: Any, ellipse_single: dict[str, Any], tmp_path: Path
) -> None:
    directory, _info = scenario("ellipse")
    shifted = measure_ellipse(directory, _db(tmp_path, "shifted"), single=ellipse_single)
    assert [m["into"] for m in shifted["merges"]] == ["session1"]
    gap, turn = shifted["transform_error"]  # T between the sessions' map frames against the ground truth
    assert gap < 1.0 and turn < 0.1
    assert shifted["s1_path"].frames > 250  # most of session 2 re-traverses session 1's path
    assert shifted["s1_path"].rate <= 0.05
    assert abs(shifted["experiences"] - shifted["single_experiences"]) <= 0.1 * shifted["single_experiences"]
    assert shifted["rmse"] <= 0.05 * shifted["extent"]
    # Fig. 12: without operation (iii) the partial map's links point at the wrong cells, so its own ground is
    # mapped anew after the merge; with it, that ground is recognised.
    unshifted = measure_ellipse(directory, _db(tmp_path, "unshifted"), "--merge-no-shift", single=ellipse_single)
    assert [m["lattice_shifted"] for m in unshifted["merges"]] == [False]
    assert unshifted["own_path"].frames == shifted["own_path"].frames > 20
    assert shifted["own_path"].created <= 1
    assert unshifted["own_path"].created >= max(0.5 * unshifted["own_experiences"], 4 * shifted["own_path"].created)
    assert unshifted["experiences"] > shifted["experiences"]


def test_ellipse_session_started_90_degrees_turned_meets_the_same_bounds(
    scenario: Any, ellipse_single: dict[str, Any], tmp_path: Path
) -> None:
    directory, info = scenario("ellipse", heading_offset_deg=90.0)
    assert info["sessions"][1]["turn_deg"] == 90.0
    turned = measure_ellipse(directory, _db(tmp_path), single=ellipse_single)
    assert len(turned["merges"]) == 1
    gap, turn = turned["transform_error"]  # the SE(3) transform between the two map frames is recovered
    assert gap < 1.0 and turn < 0.1
    assert turned["s1_path"].frames > 250 and turned["s1_path"].rate <= 0.05
    assert abs(turned["experiences"] - turned["single_experiences"]) <= 0.1 * turned["single_experiences"]
    assert turned["rmse"] <= 0.05 * turned["extent"]


def _process_all(directory: Path, info: dict[str, Any], db: str, *extra: str) -> list[dict[str, Any]]:
    return [cli_json("process", str(directory / s["log"]), "--db", db, *extra) for s in info["sessions"]]


def _connected(db: str, map_name: str, tmp_path: Path, sessions: list[str]) -> list[list[int]]:
    """Return the shortest paths (``mapserver path``) from session 1's first experience to each other session's."""
    doc_path = tmp_path / f"{map_name}.json"
    cli_json("export", "--db", db, "--map", map_name, "--format", "json", "--out", str(doc_path))
    doc = load_doc(doc_path)
    first = {name: min(e["id"] for e in doc["experiences"] if e["session"] == name) for name in sessions}
    paths = []
    for name in sessions[1:]:
        found = cli_json("path", "--db", db, "--map", map_name, "--from", str(first[sessions[0]]), "--to",
                         str(first[name]), "--weight", "distance")  # fmt: skip
        assert found["nodes"][0] == first[sessions[0]] and found["nodes"][-1] == first[name]
        paths.append(found["nodes"])
    return paths


def test_bridge_session_joins_two_maps_and_a_path_crosses(scenario: Any, tmp_path: Path) -> None:
    directory, info = scenario("bridge")
    db = _db(tmp_path)
    results = _process_all(directory, info, db)
    assert [len(r["merges"]) for r in results] == [0, 0, 2]
    assert [m["into"] for m in results[2]["merges"]] == ["session1", "session2"]
    maps = cli_json("maps", "--db", db)["maps"]
    assert [(m["name"], m["sessions"]) for m in maps] == [("session1", 3)]
    with open_database(db) as store, store.read() as conn:
        events = list_merge_events(conn=conn)
    assert [(e.mode, e.status) for e in events] == [("online", "applied")] * 2
    (path,) = _connected(db, "session1", tmp_path, ["session1", "session2"])
    assert len(path) > 10  # from the west loop over the bridge to the east loop


def test_chain5_ends_in_one_connected_map(scenario: Any, tmp_path: Path) -> None:
    directory, info = scenario("chain5")
    db = _db(tmp_path)
    results = _process_all(directory, info, db)
    assert [len(r["merges"]) for r in results[:4]] == [0, 0, 0, 0]
    assert len(results[4]["merges"]) == 4  # the outer loop joins the four inner maps
    maps = cli_json("maps", "--db", db)["maps"]
    assert [(m["name"], m["sessions"]) for m in maps] == [("session1", 5)]
    _connected(db, "session1", tmp_path, [f"session{k}" for k in range(1, 6)])


def test_cave3d_merges_once_with_depths_as_accurate_as_one_session(scenario: Any, tmp_path: Path) -> None:
    """``cave3d`` with ``poseidon`` (the neocortical front-end): one merge, 4-DoF, and the merged map
    within issue 12's 1.5× of the single route's APE, in 3-D and in depth alone (seed 0: 0.099 against 0.109 m,
    z 0.0173 against 0.0161 m; this merge leaves no merge link and is settled on the joint least squares as a merged
    map). Seeds 0–9 (``process --db``, ``export``, ``evaluate``): 10 of 10 merged, merged
    0.079–0.137 m, z 0.014–0.028 m, z ratio to the single route 0.29–1.46; ``poseidon-lvc`` 9 of 10, merged
    0.10–0.47 m, z ratio 0.53–2.59 (seed 1). Depth is held to 1.5×, not to ≤ the single route's: with LVC that was
    a fact of seed 0 alone."""
    directory, info = scenario("cave3d")
    assert info["preset"] == "poseidon"
    db = _db(tmp_path)
    results = _process_all(directory, info, db, "--preset", "poseidon")
    assert [len(r["merges"]) for r in results] == [0, 1]
    assert len(results[1]["merges"][0]["lattice_offset"]) == 4  # (x, y, z, th)
    merged, single = tmp_path / "merged.json", tmp_path / "single.json"
    cli_json("export", "--db", db, "--map", "session1", "--format", "json", "--out", str(merged))
    cli_json("process", str(directory / info["single"]["log"]), "--preset", "poseidon", "--out", str(single))
    both = tmp_path / "both.tum"
    both.write_text("".join((directory / s["ground_truth"]).read_text() for s in info["sessions"]))
    radii = ("--revisit-radius", "0.3", "--match-radius", "0.6", "--false-radius", "1.0")
    m = cli_json("evaluate", str(merged), "--ground-truth", str(both), *radii)
    s = cli_json("evaluate", str(single), "--ground-truth", str(directory / info["single"]["ground_truth"]), *radii)
    assert m["dims"] == s["dims"] == 3
    assert m["ape_rmse"] <= 1.5 * s["ape_rmse"] and m["ape_z_rmse"] <= 1.5 * s["ape_z_rmse"] < 0.05
    z, _ = experiences(load_doc(merged), "session2")
    assert np.ptp(z[:, 2]) > 0.5  # the merged session 2 keeps its dives


def test_aliased_places_merge_only_without_confirmation(scenario: Any, tmp_path: Path) -> None:
    directory, info = scenario("aliased")
    careful = _process_all(directory, info, _db(tmp_path, "careful"))
    assert [r["merges"] for r in careful] == [[], []]
    assert [r["map"] for r in careful] == ["session1", "session2"]
    paper = ("--confirm", "1", "--merge-evidence", "0", "--merge-probation", "0")
    eager = _process_all(directory, info, _db(tmp_path, "eager"), *paper)
    assert [len(r["merges"]) for r in eager] == [0, 1]  # the paper's single-frame trigger merges look-alikes
    assert eager[1]["merges"][0]["confirmations"] == 1 and eager[1]["map"] == "session1"
    one_match = _process_all(directory, info, _db(tmp_path, "one"), "--confirm", "1")  # K = 1, evidence decides
    assert [r["merges"] for r in one_match] == [[], []]


def test_symmetric_false_merge_is_rolled_back_stored_as_rejected_and_the_true_one_stands(
    scenario: Any, tmp_path: Path
) -> None:
    """Issue 12: in the point-symmetric world session 2 first meets the mirror of session 1's ground and
    merges there 180° off; its probation rolls that back, and the session merges later where it truly
    overlaps (seed 0). Both events are stored, with their status and evidence, and counted by ``maps``."""
    directory, info = scenario("symmetric")
    db = _db(tmp_path)
    results = _process_all(directory, info, db)
    merges = sorted(results[1]["merges"], key=lambda m: m["frame"])
    assert [m["status"] for m in merges] == ["rejected", "applied"]
    rejected, applied = merges
    assert rejected["evidence"]["verification"]["status"] == "rejected"
    assert applied["evidence"]["verification"]["status"] == "passed"
    turn = abs(np.angle(np.exp(1j * (rejected["transform"]["yaw"] - applied["transform"]["yaw"]))))
    assert turn > 2.5  # the rolled-back alignment was the half-turned one (sweep: 155–180° off the truth)
    (listed,) = cli_json("maps", "--db", db)["maps"]
    assert (listed["sessions"], listed["merges"]) == (2, {"applied": 1, "rejected": 1, "undone": 0, "unverified": 0})
    # the stored timeline replaced the rolled-back probation's frames by the session's own: every frame's
    # template exists in the map (a template only the rolled-back engine made would resolve to nothing)
    from mapserver.report import gather

    with open_database(db) as handle:
        frames, _created = gather(handle, listed["name"]).activations["session2"]
    assert frames.shape[0] == results[1]["frames"] and (frames[:, 1] >= 0).all()


@pytest.mark.parametrize("lookalike_m", [10.0, 40.0])
def test_a_twin_look_alike_never_merges_and_the_same_stretch_in_one_world_does(
    scenario: Any, tmp_path: Path, lookalike_m: float
) -> None:
    """Issue 12: two places sharing a copied stretch never merge; the same stretch driven in one world
    (``twin-overlap``: after it session 2 keeps to session 1's ground) still merges, once, at its true place.
    ``bench/lookalike_sweep.py`` runs the same over 10 seeds and more lengths."""
    directory, info = scenario("twin", lookalike_m=lookalike_m)
    twin = _process_all(directory, info, _db(tmp_path, "twin"))
    assert [m for m in twin[1]["merges"] if m["status"] == "applied"] == []
    directory, info = scenario("twin-overlap", lookalike_m=lookalike_m)
    overlap = _process_all(directory, info, _db(tmp_path, "overlap"))
    applied = [m for m in overlap[1]["merges"] if m["status"] == "applied"]
    assert [m["into"] for m in applied] == ["session1"]
    initial_yaw = math.radians(preset(info["preset"]).exp_initial_em_deg)
    truth = true_alignment(directory, info["sessions"][0], info["sessions"][1], initial_yaw)
    x, y, _z, yaw = (applied[0]["transform"][k] for k in ("x", "y", "z", "yaw"))
    assert math.hypot(x - truth[0], y - truth[1]) < 5.0 and abs(math.remainder(yaw - truth[3], math.tau)) < 0.35


def test_a_look_alike_holding_turns_is_rolled_back_once_the_robot_leaves_it(scenario: Any, tmp_path: Path) -> None:
    """Issue 12: with ``lookalike_turns = 1`` the look-alike holds two quarter turns, so the 45° turn rule lets
    the false merge through (frame 68, as the true one of the overlap); its probation runs on while the matches
    last and rolls it back after the structure (seed 0; sweep: 0, 1, 0, 3 of 10 survive at 5, 10, 20, 40 m,
    against 3, 5, 9, 8 with a fixed probation). The same world's true overlap still merges and passes."""
    directory, info = scenario("twin", lookalike_m=20.0, lookalike_turns=1.0)
    twin = _process_all(directory, info, _db(tmp_path, "twin"))
    assert [m["status"] for m in twin[1]["merges"]] == ["rejected"]
    assert twin[1]["merges"][0]["evidence"]["verification"]["status"] == "rejected"
    directory, info = scenario("twin-overlap", lookalike_m=20.0, lookalike_turns=1.0)
    overlap = _process_all(directory, info, _db(tmp_path, "overlap"))
    applied = [m for m in overlap[1]["merges"] if m["status"] == "applied"]
    assert [m["into"] for m in applied] == ["session1"]
    assert applied[0]["evidence"]["verification"]["status"] == "passed"


def test_offline_merge_weighs_the_rest_of_the_map(scenario: Any, tmp_path: Path, capsys: Any) -> None:
    """``mapserver merge`` offline: the twin's look-alike run is refused (the paper's K-template rule took it,
    10 of 10 seeds), the same stretch in one world merges (sweep: twin 40 of 40 refused, twin-overlap 18 of 20
    merged)."""
    from mapserver.cli import main

    outcomes = {}
    for name in ("twin", "twin-overlap"):
        directory, info = scenario(name)
        db = _db(tmp_path, name)
        for s in info["sessions"]:
            cli_json("process", str(directory / s["log"]), "--db", db, "--no-merge")
        capsys.readouterr()
        code = main(["merge", "--db", db, "--map", "session2", "--into", "session1", "--json"])
        outcomes[name] = (code, capsys.readouterr().err)
    code, err = outcomes["twin"]
    assert code == 2 and "none whose alignment the rest of the map confirms" in err
    assert outcomes["twin-overlap"][0] == 0


def test_sdr_htm_sessions_merge_at_their_true_place_and_never_into_another_cave(
    scenario: Any, tmp_path: Path
) -> None:
    """Issue 17 part 5: the neocortical front-end's maps merge through the same decision and probation.

    Session 2 of ``cave3d`` merges into session 1 (``poseidon``) at its true place and the stored merged
    map has one cortex: it restores as an engine whose every prototype is in that cortex's cells; a stop
    before the merge resumes as one run. The same session 2 never merges into session 1 of another cave
    (seed 1: the same shape, other rocks). The merge comes at frame 12, before session 2's first experience (the
    motion gate holds it): taking the robot to be at its current heading when the anchor view was seen would put
    T 35° off (0.61 rad, outside the bound below)."""
    from core import Engine
    from mapserver.processing.pipeline import process_into_store
    from mapserver.store.mapio import load_map
    from tests.mapserver.store.conftest import assert_same_arrays

    directory, info = scenario("cave3d")
    db = _db(tmp_path)
    s1, s2 = (directory / s["log"] for s in info["sessions"])
    results = [cli_json("process", str(s1), "--db", db, "--preset", "poseidon")]
    shutil.copyfile(tmp_path / "atlas.db", tmp_path / "split.db")  # session 1 alone, for the split run below
    results.append(cli_json("process", str(s2), "--db", db, "--preset", "poseidon"))
    applied = [m for m in results[1]["merges"] if m["status"] == "applied"]
    assert [m["into"] for m in applied] == ["session1"]
    initial_yaw = math.radians(preset("poseidon").exp_initial_em_deg)
    truth = true_alignment(directory, info["sessions"][0], info["sessions"][1], initial_yaw)
    x, y, _z, yaw = (applied[0]["transform"][k] for k in ("x", "y", "z", "yaw"))
    assert math.hypot(x - truth[0], y - truth[1]) < 3.0 and abs(math.remainder(yaw - truth[3], math.tau)) < 0.5
    stored = load_map(open_database(db), name="session1")
    engine = Engine.restore(preset("poseidon"), stored.snapshot)
    cells, sizes = engine.local_view.prototypes
    assert engine.local_view.tm.cells > int(cells.max())  # every prototype names cells of the one cortex
    assert (sizes > 0).mean() > 0.95 and engine.template_count == results[1]["templates"]
    # stopped halfway to its merge, the session resumes as one run: the readers' sequence state and
    # translations travel in the merge driver's state, the store rewrites the re-expressed view cells
    split = _db(tmp_path, "split")
    first = process_into_store(s2, preset("poseidon"), db_url=split, stop_after=applied[0]["frame"] // 2)
    second = process_into_store(s2, preset("poseidon"), db_url=split)
    assert first.merges == [] and [m["frame"] for m in second.merges] == [applied[0]["frame"]]
    assert_same_arrays(stored.snapshot, load_map(open_database(split), name="session1").snapshot,
                       skip=("st_next_index",))  # fmt: skip
    event = str(applied[0]["event"])  # undone as any merge; the redo gives back the map the unmerge took apart
    assert cli_json("unmerge", "--db", db, "--event", event)["frames"] == applied[0]["frame"] + 1
    assert cli_json("merge", "--db", db, "--redo", event)["map"] == "session1"
    assert_same_arrays(stored.snapshot, load_map(open_database(db), name="session1").snapshot)
    other = tmp_path / "other"
    simulate_once("cave3d", other, seed=1, only=["session1"])  # only the log this needs
    alien = _db(tmp_path, "alien")
    cli_json("process", str(other / "session1.bag"), "--db", alien, "--preset", "poseidon")
    result = cli_json("process", str(directory / "session2.bag"), "--db", alien, "--preset", "poseidon")
    assert [m for m in result["merges"] if m["status"] == "applied"] == []


def test_poseidon_sdr_closes_the_caves_loops_that_the_whole_image_at_the_thesis_gate_never_closes(
    scenario: Any,
) -> None:
    """Issue 17: ``poseidon``'s weight-free encoder sees the cave at 16×6 with I_min 8 (docs/journal.md,
    "`poseidon-sdr`'s weight-free encoder sees the cave at 16×6, gate I_min 8").

    The ``cave3d`` single route (seed 0) then closes loops and its map is as accurate as LVC's (0.19 m; here
    5 closures, 0.18 m); with the image at ``poseidon-lvc``'s 64×24 and the thesis's I_min 12 a revisit
    0.2–0.4 m off keeps too few descriptor bits: no closure, dead reckoning, 0.78 m."""
    directory, info = scenario("cave3d")
    log, truth = directory / info["single"]["log"], directory / info["single"]["ground_truth"]
    figures, thesis = {}, ("--set", "template_x_size=64,template_y_size=24,sv_min_intersection=12")
    for tag, extra in (("now", ()), ("thesis", thesis)):
        doc = directory / f"poseidon-sdr-{tag}.json"
        run = cli_json("process", str(log), "--preset", "poseidon", *extra, "--out", str(doc))
        figures[tag] = (run["loop_closures"], cli_json("evaluate", str(doc), "--ground-truth", str(truth))["ape_rmse"])
    assert figures["now"][0] >= 3 and figures["now"][1] < 0.3
    assert figures["thesis"][0] == 0 and figures["thesis"][1] > 0.5



def _twin_worlds_stored_apart(tmp_path: Path, seed: int, lookalike_m: float) -> dict[str, str]:
    """Simulate ``twin`` and ``twin-overlap`` (a look-alike holding turns) and store each one's sessions 1 and 2 as
    two maps (``process --no-merge``, LVC, ``circle``); return each scenario's database."""
    databases = {}
    for name in ("twin", "twin-overlap"):
        directory = tmp_path / name
        info = simulate_once(name, directory, seed=seed, params={"lookalike_m": lookalike_m, "lookalike_turns": 1.0},
                             only=SESSIONS)
        databases[name] = _db(tmp_path, name)
        for s in info["sessions"][:2]:
            cli_json("process", str(directory / s["log"]), "--db", databases[name], "--no-merge")
    return databases


def _merge_offline(db: str) -> tuple[int, str]:
    """``mapserver merge`` session 2's map into session 1's: (exit code, stderr)."""
    return cli_code("merge", "--db", db, "--map", "session2", "--into", "session1")


def test_an_offline_merge_into_a_look_alike_holding_turns_fails_the_probation_online_merges_run(tmp_path: Path) -> None:
    """Issue 12 offline: ``twin`` with a 20 m look-alike holding turns, seed 4 (LVC, ``circle``). A's
    whole map weighed against B passed the offline test (28.3 m of matching views, 6.5 m failing: score 15.2 m
    for 4 m needed) and the maps of two places became one (2 of 10 seeds; 1 of 10 at 10 and at 40 m; ``sdr-htm``
    1 and 3). After the match both chains meet a run of 4.1–4.4 m of failing views, as a probation would online,
    so the merge is refused. Must still: the same stretch in one world (``twin-overlap``, seed 4) merges."""
    databases = _twin_worlds_stored_apart(tmp_path, seed=4, lookalike_m=20.0)
    code, err = _merge_offline(databases["twin"])
    assert code == 2 and "failing views in a row" in err  # must not: the look-alike
    assert _merge_offline(databases["twin-overlap"])[0] == 0  # must still: the true overlap


def test_an_offline_merge_whose_two_maps_part_in_disagreement_past_the_look_alike_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 12 offline: ``twin`` with a 10 m look-alike holding turns, seed 6 (LVC, ``circle``), passes every run
    rule: 22.8 m of matching views spanning 177°, and past the stretch's far end A meets only 2.1 m of failing
    views in a row and B 3.2 m before each leaves the other's ground, under every run rule's 4 m. Both maps drive
    on over each other's ground and both disagree, so their failing metres add up (5.2 m) and the merge is
    refused. Paired: without the rule the same maps merge; the same stretch in one world
    (``twin-overlap``, seed 6) still merges."""
    from mapserver.merge.offline_evidence import OfflineEvidence

    databases = _twin_worlds_stored_apart(tmp_path, seed=6, lookalike_m=10.0)
    code, err = _merge_offline(databases["twin"])
    assert code == 2 and "both maps drive on over each other's ground" in err  # must not: the look-alike
    assert _merge_offline(databases["twin-overlap"])[0] == 0  # must still: the true overlap
    monkeypatch.setattr(OfflineEvidence, "parting_m", property(lambda self: 0.0))
    assert _merge_offline(databases["twin"])[0] == 0  # the rule is what refuses it


def test_an_offline_window_that_closes_no_loop_runs_past_a_100_m_look_alike_to_where_it_ends(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 12 offline: ``twin`` with a 100 m look-alike holding turns, seed 2 (LVC, ``circle``), past the
    issue's range. Its best alignment still matches at 8 probation distances (``PROBATION_CAP``; 96.5 m after the
    match on A's chain and 96.8 m on B's): a window ending there ends inside the look-alike and the maps of two
    places become one (transform 155 m off). A window whose hits close no loop on the other map runs to 16
    probation distances (``OPEN_PROBATION_CAP``), as an online probation does: it reaches the look-alike's end and
    meets 18.6 m of failing views in a row. Paired: with ``PROBATION_CAP`` for that window the same maps merge; the
    same stretch in one world (``twin-overlap``, seed 2, whose window passes 133 m after the match) still merges."""
    from mapserver.merge import offline_evidence

    databases = _twin_worlds_stored_apart(tmp_path, seed=2, lookalike_m=100.0)
    code, err = _merge_offline(databases["twin"])
    assert code == 2 and "failing views in a row" in err  # must not: the look-alike
    assert _merge_offline(databases["twin-overlap"])[0] == 0  # must still: the true overlap
    monkeypatch.setattr(offline_evidence, "OPEN_PROBATION_CAP", offline_evidence.PROBATION_CAP)
    assert _merge_offline(databases["twin"])[0] == 0  # the longer window is what refuses it


def test_sdr_htm_maps_merge_offline_by_their_codes_undo_and_redo_exactly_and_never_into_another_cave(
    scenario: Any, tmp_path: Path
) -> None:
    """``mapserver merge`` of two stored ``sdr-htm`` maps: ``cave3d`` seed 0, both sessions
    processed alone (``--no-merge``, ``poseidon``). Session 2's map merges into session 1's at the true place
    (``bench/offline_merge_sweep.py cave3d``: 10 of 10, merged maps 0.11–0.33 m) with every view cell kept as a
    prototype of the one cortex; ``unmerge`` restores both maps bit for bit and ``merge --redo`` makes the same
    merged map again. Must not: session 2 against session 1 of another cave (seed 1) is refused (exit 2)."""
    from core import Engine
    from mapserver.store.mapio import load_map
    from tests.mapserver.store.conftest import assert_same_arrays

    directory, info = scenario("cave3d")
    db, sdr = _db(tmp_path), ("--preset", "poseidon", "--no-merge")
    for session in info["sessions"][:2]:
        cli_json("process", str(directory / session["log"]), "--db", db, *sdr, "--map", session["name"])
    alone = {name: load_map(open_database(db), name=name).snapshot for name in ("session1", "session2")}
    merged = cli_json("merge", "--db", db, "--map", "session2", "--into", "session1")
    assert merged["merged"] and merged["map"] == "session1"
    with open_database(db) as database, database.read() as conn:
        (event,) = list_merge_events(conn=conn)
    initial_yaw = math.radians(preset("poseidon").exp_initial_em_deg)
    truth = true_alignment(directory, info["sessions"][0], info["sessions"][1], initial_yaw)
    assert math.hypot(event.transform[0] - truth[0], event.transform[1] - truth[1]) < 2.0
    assert abs(math.remainder(event.yaw - truth[3], math.tau)) < 0.2
    evidence = event.details["evidence"]["offline"]
    assert evidence["passed"] and evidence["hit_m"] > 5 * evidence["miss_m"]
    stored = load_map(open_database(db), name="session1").snapshot
    engine = Engine.restore(preset("poseidon"), stored)
    cells, sizes = engine.local_view.prototypes
    assert engine.local_view.tm.cells > int(cells.max()) and (sizes > 0).mean() > 0.95  # one cortex's cells
    doc, both = directory / "offline-merged.json", directory / "offline-both.tum"
    cli_json("export", "--db", db, "--map", "session1", "--format", "json", "--out", str(doc))
    both.write_text("".join((directory / s["ground_truth"]).read_text() for s in info["sessions"][:2]))
    assert cli_json("evaluate", str(doc), "--ground-truth", str(both))["ape_rmse"] < 0.25
    cli_json("unmerge", "--db", db, "--event", str(event.id))
    for name, snapshot in alone.items():
        again = load_map(open_database(db), name=name).snapshot
        print(name, [k for k in snapshot if not np.array_equal(np.asarray(snapshot[k]), np.asarray(again.get(k)))])
        assert_same_arrays(snapshot, again)
    assert cli_json("merge", "--db", db, "--redo", str(event.id))["map"] == "session1"
    assert_same_arrays(stored, load_map(open_database(db), name="session1").snapshot)
    other = tmp_path / "other"
    simulate_once("cave3d", other, seed=1, only=["session1"])  # only the log this needs
    alien = _db(tmp_path, "alien")
    cli_json("process", str(other / "session1.bag"), "--db", alien, *sdr, "--map", "other")
    cli_json("process", str(directory / "session2.bag"), "--db", alien, *sdr, "--map", "session2")
    code, err = cli_code("merge", "--db", alien, "--map", "session2", "--into", "other")
    assert code == 2 and "ERROR" in err


def _merged_ape(
    directory: Path, info: dict[str, Any], db: str, *extra: str, statuses: tuple[str, ...] = ("applied",)
) -> float:
    """Process both sessions into ``db`` and return the merged map's APE against both ground truths."""
    result = _process_all(directory, info, db, *extra)[1]
    assert tuple(m["status"] for m in sorted(result["merges"], key=lambda m: m["frame"])) == statuses
    doc, truth = directory / f"{result['map']}-{len(extra)}.json", directory / "both.tum"
    cli_json("export", "--db", db, "--map", result["map"], "--format", "json", "--out", str(doc))
    truth.write_text("".join((directory / s["ground_truth"]).read_text() for s in info["sessions"][:2]))
    return float(cli_json("evaluate", str(doc), "--ground-truth", str(truth))["ape_rmse"])


def test_a_true_merge_bent_by_its_closures_headings_is_kept_by_the_joint_least_squares(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``twin-overlap`` 40 m, seed 7 (docs/journal.md, "three tries at the heading errors of forward-view closures"):
    every link of the merged map lies within 0.55 m of the truth, but RatSLAM's fixed point turns the closures'
    heading errors (9–17°) into a position misclosure, the robust check switches the true merge link 165 → 1 off,
    and session 2's approach hangs from one end: APE 11.19 m (``--set merge_relax_joint=0``). A merged map is
    checked and settled at the joint least squares by default: the check keeps the merge link, and the settled map
    is within 1.5 m. The merge link's switch prior in the TLS cost also keeps it on RatSLAM's fixed point (1.72 m);
    without the prior (and without the joint least squares, and the closures and ties between the sessions facing
    the views' headings, ``merge_view_heading``: 7.29 m with them) the failure is back."""
    directory = tmp_path / "twin-overlap"
    info = simulate_once("twin-overlap", directory, seed=7, params={"lookalike_m": 40.0}, only=SESSIONS)
    assert _merged_ape(directory, info, _db(tmp_path, "joint")) < 1.5
    assert _merged_ape(directory, info, _db(tmp_path, "ratslam"), "--set", "merge_relax_joint=0") < 2.0
    monkeypatch.setattr(robust_module, "MERGE_LINK_HOLD", 0.0)
    monkeypatch.setattr(online_module, "TIE_HITS", False)  # the ties alone hold it too (1.58 m)
    bare = _db(tmp_path, "bare")
    assert _merged_ape(directory, info, bare, "--set", "merge_relax_joint=0,merge_view_heading=0") > 10.0


def test_a_merge_that_identified_every_partial_experience_is_settled_as_a_merged_map(tmp_path: Path) -> None:
    """``symmetric-overlap`` seed 15 (docs/journal.md, "a merge that identified every partial experience makes a
    merged map"): session 2 merges at frame 8, and the merge identifies its partial map's experiences with stored
    ones, so the merged map holds no merge link. Taken for a single session's map, it would be settled at RatSLAM's
    fixed point: 0.99 m APE against 0.43 m for the single route and 0.52 m at the joint least squares of the same
    active links. Two sessions' experiences make it a merged map: 0.52 m (0.45 m with ``merge_view_heading``'s view
    headings). With ``merge_relax_joint=0`` (RatSLAM's fixed point for every map) and ``merge_view_heading=0`` (the
    closures and ties between the sessions facing the robot's odometry, not the views' headings: 0.59 m with them)
    the failure is back."""
    directory = tmp_path / "symmetric-overlap"
    info = simulate_once("symmetric-overlap", directory, seed=15, only=SESSIONS)
    assert _merged_ape(directory, info, _db(tmp_path, "joint")) < 0.6
    ratslam = _db(tmp_path, "ratslam")
    assert _merged_ape(directory, info, ratslam, "--set", "merge_relax_joint=0,merge_view_heading=0") > 0.9


def test_a_late_merge_ties_the_sessions_own_copy_of_the_stored_ground_to_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``twin-overlap`` turns alike 60 m, seed 4 (docs/journal.md, "late merges tie the session's own copy of the stored
    ground"): session 2 drives 110 m of session 1's ground before its merge at frame 270 wins over the look-alike's
    rival. The merge identified only the experiences its anchor's view pairs put within half a link of each other: that
    copy of the stored ground hung from the anchor, and the merged map came out at 6.92 m APE (the single route 1.61 m;
    session 1 alone 3.26 m). A merge link per hit of the winning hypothesis (``Match.ties``) holds the copy along its
    length: 2.30 m."""
    directory = tmp_path / "twin-overlap"
    info = simulate_once("twin-overlap", directory, seed=4, params={"lookalike_m": 60.0, "lookalike_turns": 1.0},
                         only=SESSIONS)
    assert _merged_ape(directory, info, _db(tmp_path, "tied")) < 3.0
    monkeypatch.setattr(online_module, "TIE_HITS", False)
    assert _merged_ape(directory, info, _db(tmp_path, "anchored")) > 5.0


def test_a_probation_follows_the_engines_closures_to_the_end_of_a_look_alike_longer_than_its_cap(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``twin`` turns alike 100 m, seed 1 (beyond the issue's 5–40 m; docs/journal.md, "a probation follows the engine's
    own closures onto the stored map"): the false merge at frame 68 passed its probation 184 m later, its prediction
    having left session 1's places 24 m into the look-alike while the engine kept closing onto them (39 closures
    3.7–16.9 m from it). Re-placed by each agreeing closure (:meth:`Probation._follow_link`), the prediction stays on
    them to the look-alike's end, where the views part, and the merge is rolled back; without it, the merge stays."""
    directory = tmp_path / "twin"
    info = simulate_once("twin", directory, seed=1, params={"lookalike_m": 100.0, "lookalike_turns": 1.0},
                         only=SESSIONS)
    followed = _process_all(directory, info, _db(tmp_path, "followed"))[1]["merges"]
    assert [m["status"] for m in followed] == ["rejected"]
    assert "mismatches in a row" in followed[0]["evidence"]["verification"]["reason"]
    monkeypatch.setattr(verify_module, "FOLLOW_LINKS", False)
    unfollowed = _process_all(directory, info, _db(tmp_path, "unfollowed"))[1]["merges"]
    assert [m["status"] for m in unfollowed] == ["applied"]


def test_a_merged_sessions_own_first_pass_closes_within_the_merges_lever_arm(tmp_path: Path) -> None:
    """``symmetric`` seed 1 (docs/journal.md, "a closure gate as wide as the merge's lever arm"): session 2 merges at
    frame 79 with the view's heading 8° off; its first pass, 50–80 m of path before the anchor, lands 4–5 lattice
    cells from where the packet meets it again (OpenRatSLAM's closure gate there: 4), so the second pass cannot close
    onto it and relocalises at the mirror place. Widening the gate by ``merge_lattice_slack`` (0.2) times each
    experience's lattice distance from the merge anchor, the second pass closes onto it: merged APE 1.17 m without the
    slack, 0.56 m with it (the single route: 0.41 m; at RatSLAM's fixed point, ``merge_relax_joint=0``: 1.32 and
    0.74 m). Measured without the closures and ties between the sessions facing the way the views' column shifts say
    (``merge_view_heading``), as those figures were; with them the map without the slack is 0.50 m as well."""
    directory = tmp_path / "symmetric"
    info = simulate_once("symmetric", directory, seed=1, only=SESSIONS)
    both = ("rejected", "applied")
    rigid = _db(tmp_path, "rigid")
    without = _merged_ape(directory, info, rigid, "--set", "merge_lattice_slack=0,merge_view_heading=0", statuses=both)
    assert without > 1.0
    assert _merged_ape(directory, info, _db(tmp_path, "lever"), statuses=both) < 0.7


@pytest.mark.parametrize("seed", [4, 7])
def test_an_offline_merge_does_not_refold_what_each_map_unfolded_alone(tmp_path: Path, seed: int) -> None:
    """``symmetric``, sessions stored alone (``--no-merge``, ``circle``), then ``merge --map session2 --into
    session1`` (such merges refolded 4 of 10 merged maps to 16–17.7 m though every merge was at the true place;
    docs/journal.md, "an offline merge no longer folds again what each map unfolded alone"). Session
    2's own map holds false relocalisations onto the mirror sector, which its robust check undid (the odometry
    link each made switched off, its reckoning link on); the merge identified experiences at their ends and
    folded the map again — seed 4: the switched-off odometry link came back on as a merge link and won the check
    on rounding noise against the reckoning link (a tie: either alone joins session 2's first lap without
    strain); seed 7: the reckoning link was dropped, so the odometry link it stood in for could not be switched
    off. Merged APE 2.61 / 4.14 m (3.19 / 3.05 m without the offline closures of the next test; sessions
    alone 1.22 and 3.17 / 1.60 and 3.93 m; refolded 15.97 / 17.48 m).
    Must still: the merge is made, at the true place."""
    directory = tmp_path / "symmetric"
    info = simulate_once("symmetric", directory, seed=seed, only=SESSIONS)
    db = _db(tmp_path)
    apes = []
    for s in info["sessions"][:2]:
        cli_json("process", str(directory / s["log"]), "--db", db, "--no-merge", "--map", s["name"])
        doc = directory / f"{s['name']}.json"
        cli_json("export", "--db", db, "--map", s["name"], "--format", "json", "--out", str(doc))
        truth_tum = str(directory / s["ground_truth"])
        apes.append(float(cli_json("evaluate", str(doc), "--ground-truth", truth_tum)["ape_rmse"]))
    merged = cli_json("merge", "--db", db, "--map", "session2", "--into", "session1")
    assert merged["merged"]  # must still
    with open_database(db) as database, database.read() as conn:
        (event,) = list_merge_events(conn=conn)
    initial_yaw = math.radians(preset(info["preset"]).exp_initial_em_deg)
    truth = true_alignment(directory, info["sessions"][0], info["sessions"][1], initial_yaw)
    assert math.hypot(event.transform[0] - truth[0], event.transform[1] - truth[1]) < 5.0
    doc, both = directory / "merged.json", directory / "both.tum"
    cli_json("export", "--db", db, "--map", "session1", "--format", "json", "--out", str(doc))
    both.write_text("".join((directory / s["ground_truth"]).read_text() for s in info["sessions"][:2]))
    ape = float(cli_json("evaluate", str(doc), "--ground-truth", str(both))["ape_rmse"])
    assert ape < 1.25 * max(apes)


def test_an_offline_merge_closes_loops_where_the_maps_overlap_and_redo_closes_the_same(tmp_path: Path) -> None:
    """``twin-overlap`` 20 m, seed 1, sessions stored alone (``circle``), then ``merge --map session2 --into
    session1``. The merge identifies experiences in its confirmation window only; the evidence walk
    found session 2's views matching session 1's along the whole overlap, and each such place now becomes a
    loop link (as RatSLAM would have closed online), decided by the robust check like any closure: merged APE
    3.38 m without them (sessions alone 1.45 and 0.67 m), 0.54 m with them. ``unmerge`` then ``merge --redo``
    makes the same map bit for bit (the closures are in the event). Must still: merged, and one map of both
    sessions' ground within 1 m. ``--merge-evidence 0`` (the paper's rule, as multisession-ratslam merges) adds none."""
    from mapserver.store.mapio import load_map
    from tests.mapserver.store.conftest import assert_same_arrays

    directory = tmp_path / "twin-overlap"
    info = simulate_once("twin-overlap", directory, seed=1, params={"lookalike_m": 20.0}, only=SESSIONS)
    db = _db(tmp_path)
    for s in info["sessions"][:2]:
        cli_json("process", str(directory / s["log"]), "--db", db, "--no-merge", "--map", s["name"])
    assert cli_json("merge", "--db", db, "--map", "session2", "--into", "session1")["merged"]
    with open_database(db) as database, database.read() as conn:
        (event,) = list_merge_events(conn=conn)
    assert len(event.details["closures"]) > 10
    doc, both = directory / "merged.json", directory / "both.tum"
    cli_json("export", "--db", db, "--map", "session1", "--format", "json", "--out", str(doc))
    both.write_text("".join((directory / s["ground_truth"]).read_text() for s in info["sessions"][:2]))
    assert cli_json("evaluate", str(doc), "--ground-truth", str(both))["ape_rmse"] < 1.0
    stored = load_map(open_database(db), name="session1").snapshot
    cli_json("unmerge", "--db", db, "--event", str(event.id))
    assert cli_json("merge", "--db", db, "--redo", str(event.id))["map"] == "session1"
    assert_same_arrays(stored, load_map(open_database(db), name="session1").snapshot)
    cli_json("unmerge", "--db", db, "--event", str(event.id))  # the paper's rule merges as multisession-ratslam does
    assert cli_json("merge", "--db", db, "--map", "session2", "--into", "session1", "--merge-evidence", "0")["merged"]
    with open_database(db) as database, database.read() as conn:
        paper = list_merge_events(conn=conn)[-1]
    assert paper.id != event.id and paper.details["closures"] == []

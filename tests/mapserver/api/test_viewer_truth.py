"""Ground truth kept per session, the viewer's overlay and its APE (the same figure as ``mapserver evaluate``),
and each session's start and end in the graph view."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapserver.api.viewdata import session_ends
from mapserver.api.viewtruth import in_map_frame, thin
from mapserver.cli import main
from mapserver.errors import InputError
from mapserver.formats import read_tum, write_tum
from mapserver.params import resolve_params
from mapserver.processing import pipeline
from mapserver.store import open_database
from mapserver.store.ground_truth import decimate_ground_truth, get_ground_truth, session_id_by_name
from tests.mapserver.api.conftest import Api
from tests.mapserver.api.logs import strip_truth, write_strip_log
from tests.mapserver.api.test_viewer_api import graph_of

TURN, SHIFT = 0.5, (5.0, -3.0)  # the ground truth's frame: turned 0.5 rad and shifted from the odometry's
LAPS, TRUTH_HZ = 1.3, 40.0


def rows_of(n: int, dt: float) -> np.ndarray:
    rows = np.zeros((n, 8))
    rows[:, 0] = 100.0 + dt * np.arange(n)
    rows[:, 1] = np.arange(n)
    rows[:, 7] = 1.0
    return rows


def test_decimation_keeps_the_first_pose_of_each_interval_and_the_last() -> None:
    rows = rows_of(40, 0.25)  # 100.00, 100.25, ..., 109.75 s; one kept per second: 100, 101, ..., 109, and 109.75
    kept = decimate_ground_truth(rows[::-1], spacing_s=1.0)  # given in any order, kept in stamp order
    assert kept[:, 0].tolist() == [100.0 + k for k in range(10)] + [109.75]
    assert kept[:, 1].tolist() == [4.0 * k for k in range(10)] + [39.0]
    exact = rows_of(21, 0.1)  # at exactly 1 / spacing Hz every pose stays, whatever the rounding of the stamps
    assert decimate_ground_truth(exact, spacing_s=0.1).shape[0] == 21


def test_decimation_caps_the_rows_and_refuses_what_is_not_ground_truth() -> None:
    kept = decimate_ground_truth(rows_of(1001, 0.1), max_rows=12)  # 100 s: the spacing widens to 10 s
    assert kept.shape[0] <= 12 and kept[0, 0] == 100.0 and kept[-1, 0] == pytest.approx(200.0)
    assert np.allclose(np.diff(kept[:-1, 0]), 10.0)
    for bad in (np.zeros((0, 8)), np.zeros((3, 7)), np.full((2, 8), np.nan)):
        with pytest.raises(InputError):
            decimate_ground_truth(bad)


def test_each_session_starts_and_ends_at_its_first_and_last_experience_in_time() -> None:
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [5.0, 5.0], [6.0, 5.0]])
    g = graph_of(xy, [], np.array([0, 0, 1, 1, 0]))  # stamps 0..4: session 0 is 0, 1, 4; session 1 is 2, 3
    ends = session_ends(g)
    assert [(e["session"], e["start"]["id"], e["end"]["id"]) for e in ends] == [(0, 0, 4), (1, 2, 3)]
    assert ends[0]["end"] == {"id": 4, "x": 6.0, "y": 5.0}
    side = session_ends(g, "xz")  # the side view's plane: x and z (0 here)
    assert side[1]["start"] == {"id": 2, "x": 2.0, "y": 0.0}


def test_the_overlay_undoes_the_alignment_and_thins_evenly() -> None:
    rows = np.zeros((2, 8))
    rows[:, 1:4] = [[1.0, 2.0, 3.0], [0.0, 0.0, 1.0]]
    quarter = {"rotation": [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], "translation": [1.0, 0.0, 1.0]}
    # p_map = Rᵀ(p − t): (1, 2, 3) − t = (0, 2, 2), turned back a quarter: (2, 0, 2); planar maps drop z first
    assert in_map_frame(rows, quarter, 3).tolist() == [[2.0, 0.0, 2.0], [0.0, 1.0, 0.0]]
    assert in_map_frame(rows, quarter, 2).tolist() == [[2.0, 0.0, -1.0], [0.0, 1.0, -1.0]]
    assert thin(5, 10).tolist() == [0, 1, 2, 3, 4] and thin(101, 5).tolist() == [0, 25, 50, 75, 100]


def process(log: Path, db_url: str, name: str) -> None:
    pipeline.process_into_store(log, resolve_params("irat"), db_url=db_url, map_name=name, merge=False)


def evaluate_cli(capsys: Any, doc: Path, truth: Path, session: str) -> dict[str, Any]:
    capsys.readouterr()
    assert main(["evaluate", str(doc), "--ground-truth", str(truth), "--session", session, "--json"]) == 0
    result: dict[str, Any] = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    return result


def stored_truth(db_url: str, session: str) -> np.ndarray | None:
    with open_database(db_url) as db, db.read() as conn:
        return get_ground_truth(conn=conn, session_id=session_id_by_name(conn=conn, name=session))


def test_a_log_with_ground_truth_keeps_it_and_the_overlay_gives_the_ape_of_evaluate(
    api: Api, tmp_path: Path, capsys: Any
) -> None:
    log = write_strip_log(tmp_path / "truth.bag", laps=LAPS, truth_hz=TRUTH_HZ, truth_frame=(TURN, *SHIFT))
    process(log, api.db_url, "truth")
    # kept: one pose per 0.1 s of the 40 Hz topic (every 4th) and the last
    full = strip_truth(LAPS * 24.0, TRUTH_HZ, (TURN, *SHIFT))
    stored = stored_truth(api.db_url, "truth")
    assert stored is not None and stored.shape[0] == len(range(0, len(full), 4)) + ((len(full) - 1) % 4 != 0)
    assert stored[1, 1] == full[4].x and stored[-1, 2] == full[-1].y
    body = api.client.get("/v1/maps/truth/ground-truth", headers=api.read).json()
    assert body["without"] == [] and [s["name"] for s in body["sessions"]] == ["truth"]
    mine = body["sessions"][0]
    assert mine["rows"] == mine["drawn"] == stored.shape[0] and mine["error"] is None
    # the same figures as `mapserver evaluate` of the exported map against the stored ground truth, exactly
    doc = tmp_path / "truth.json"
    doc.write_bytes(api.client.get("/v1/maps/truth/export", params={"format": "json"}, headers=api.read).content)
    tum = tmp_path / "stored.tum"
    write_tum(tum, stored[:, 0], stored[:, 1:4], stored[:, 4:8])
    expected = evaluate_cli(capsys, doc, tum, "truth")
    for key in ("ape_rmse", "ape_mean", "ape_max", "hausdorff", "aligned", "experiences", "odometry_ape_rmse",
                "alignment", "dims", "rpe"):  # fmt: skip
        assert mine["ape"][key] == expected[key], key
    # and within a millimetre of evaluating against the full 40 Hz topic
    every = tmp_path / "full.tum"
    write_tum(every, [s.stamp_ns * 1e-9 for s in full], [[s.x, s.y, s.z] for s in full],
              [[s.qx, s.qy, s.qz, s.qw] for s in full])  # fmt: skip
    assert abs(evaluate_cli(capsys, doc, every, "truth")["ape_rmse"] - mine["ape"]["ape_rmse"]) < 1e-3
    # the alignment finds the frame the ground truth was written in (turned 0.5 rad from the odometry's, whose
    # first heading the map draws at exp_initial_em_deg, 140° for irat), and the overlay is the ground truth
    # brought back into the map's frame: R·p + t gives the stored positions again
    R = np.asarray(mine["ape"]["alignment"]["rotation"])
    t = np.asarray(mine["ape"]["alignment"]["translation"])
    turn = TURN - math.radians(resolve_params("irat").exp_initial_em_deg)
    assert math.atan2(R[1, 0], R[0, 0]) == pytest.approx(turn, abs=0.05)
    back = np.column_stack([mine["x"], mine["y"], np.zeros(len(mine["x"]))]) @ R.T + t
    assert np.abs(back[:, :2] - stored[:, 1:3]).max() < 1e-3
    # a limit thins the points evenly, the first and the last kept
    few = api.client.get("/v1/maps/truth/ground-truth", params={"limit": 10}, headers=api.read).json()["sessions"][0]
    assert few["drawn"] == len(few["x"]) <= 10 and few["rows"] == stored.shape[0]
    assert (few["x"][0], few["x"][-1]) == (mine["x"][0], mine["x"][-1]) and few["ape"] == mine["ape"]


def test_without_ground_truth_the_overlay_is_empty_and_a_tum_file_adds_it(
    api: Api, tmp_path: Path, capsys: Any
) -> None:
    process(write_strip_log(tmp_path / "plain.bag", laps=LAPS), api.db_url, "plain")
    assert stored_truth(api.db_url, "plain") is None
    empty = api.client.get("/v1/maps/plain/ground-truth", headers=api.read)
    assert empty.status_code == 200 and empty.json() == {"sessions": [], "without": ["plain"], "view": "xy"}
    # the refusals: no token, unknown map, a limit out of range
    assert api.client.get("/v1/maps/plain/ground-truth").status_code == 401
    assert api.client.get("/v1/maps/nope/ground-truth", headers=api.read).status_code == 404
    for limit in (1, 20_001):
        refused = api.client.get("/v1/maps/plain/ground-truth", params={"limit": limit}, headers=api.read)
        assert refused.status_code == 422
    # `mapserver ground-truth SESSION GT.tum` gives it to the stored session; the overlay follows at once
    full = strip_truth(LAPS * 24.0, 10.0, (TURN, *SHIFT))
    given = tmp_path / "given.tum"
    write_tum(given, [s.stamp_ns * 1e-9 for s in full], [[s.x, s.y, s.z] for s in full],
              [[s.qx, s.qy, s.qz, s.qw] for s in full])  # fmt: skip
    assert main(["ground-truth", "plain", str(given), "--db", api.db_url]) == 0
    stored = stored_truth(api.db_url, "plain")
    assert stored is not None and stored.shape[0] == len(full)  # 10 Hz: every pose kept
    added = api.client.get("/v1/maps/plain/ground-truth", headers=api.read).json()
    assert added["without"] == [] and added["sessions"][0]["rows"] == len(full)
    doc = tmp_path / "plain.json"
    doc.write_bytes(api.client.get("/v1/maps/plain/export", params={"format": "json"}, headers=api.read).content)
    assert added["sessions"][0]["ape"]["ape_rmse"] == evaluate_cli(capsys, doc, given, "plain")["ape_rmse"]
    # the file round-trips through --out; a session that is not there is an input error (exit 2)
    out = tmp_path / "out.tum"
    assert main(["ground-truth", "plain", "--db", api.db_url, "--out", str(out)]) == 0
    assert np.array_equal(read_tum(out).positions_xyz, read_tum(given).positions_xyz)
    assert main(["ground-truth", "nope", str(given), "--db", api.db_url]) == 2
    assert main(["ground-truth", "plain", "--db", api.db_url]) == 2  # neither a file nor --out

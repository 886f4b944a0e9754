"""Manual links (``mapserver link``, ``POST /v1/maps/{name}/links``): checked, flagged, merged, undone.

The single-map case: one lap and a quarter of the ``loop`` simulation at half scale (34.6 m lap) processed with a
view-matching threshold no view meets, so that the revisit is never recognised (as a revisit in the opposite
direction or by night is not): 87 experiences, no loop closure, the map is the odometry's. The stated transform
of a consistent link is the ground truth's: the pose of experience 69 (the start, one lap later) in experience
0's frame, read from the ground-truth trajectory at their stamps. The two-map case: the Virtual Tour's two
sessions (``ellipse`` at half scale) stored as two maps, linked at the pair of experiences nearest in the world.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from scipy.spatial.transform import Rotation

from core import LinkKind, preset
from core.links import SWITCHABLE_KINDS
from core.se3 import compose, relative
from mapserver.api import Settings, create_app
from mapserver.atlas.manual_links import LinkRequest, link_experiences
from mapserver.atlas.undo import redo_merge, unmerge
from mapserver.errors import ConflictError
from mapserver.evaluation import evaluate_map, interpolate_poses
from mapserver.formats import Trajectory, read_tum
from mapserver.formats.g2o import g2o_text
from mapserver.processing import pipeline
from mapserver.store import get_map, load_map, open_database
from mapserver.store.export import export_map, map_document
from mapserver.store.manual_links import manual_links
from mapserver.store.tokens import create_token
from tests.mapserver.merge.scenario_metrics import cli_code, cli_json
from tests.mapserver.store.conftest import assert_same_arrays, db_url  # noqa: F401
from tests.simulations import simulate_once

BLIND = preset("circle").replace(vt_match_threshold=1e-4)  # no view ever matches another
LAP_START, LAP_END = 0, 69  # experience 69 is the start again, one lap later


def _true_poses(gt: Trajectory, stamps: list[float]) -> np.ndarray:
    """(x, y, z, yaw) of the ground truth at each stamp (positions interpolated, heading of the nearest sample)."""
    xyz = interpolate_poses(gt, stamps)
    nearest = [int(np.argmin(np.abs(gt.stamps_s - s))) for s in stamps]
    yaw = Rotation.from_quat(gt.quat_xyzw[nearest]).as_euler("zyx")[:, 0]
    return np.column_stack([xyz, yaw])


def _doc(url: str, name: str) -> dict[str, Any]:
    with open_database(url) as db:
        return map_document(load_map(db, name=name))


def _stated(url: str, gt: Trajectory, name: str, a: int, b: int, doc_b: str | None = None) -> tuple[float, ...]:
    """The true pose of experience ``b`` (of map ``doc_b``, default ``name``) in experience ``a``'s frame."""
    stamp_a = _doc(url, name)["experiences"][a]["stamp"]
    stamp_b = _doc(url, doc_b or name)["experiences"][b]["stamp"]
    pa, pb = _true_poses(gt, [stamp_a, stamp_b])
    return tuple(float(v) for v in relative(pa, pb))


@pytest.fixture(scope="module")
def lap(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Trajectory]:
    """The blind map's database (copy it before writing) and the ground truth."""
    directory = tmp_path_factory.mktemp("lap")
    simulate_once("loop", directory, scale=0.5, params={"laps": 1.25}, only=["single"])
    url = f"sqlite:///{directory / 'blind.db'}"
    result = pipeline.process_into_store(directory / "single.bag", BLIND, db_url=url, map_name="blind")
    assert (result.summary()["experiences"], result.summary()["loop_closures"]) == (87, 0)
    return directory / "blind.db", read_tum(directory / "single.tum")


def _copy(lap: tuple[Path, Trajectory], tmp_path: Path) -> str:
    shutil.copy(lap[0], tmp_path / "blind.db")
    return f"sqlite:///{tmp_path / 'blind.db'}"


def _ape(url: str, name: str, gt: Trajectory) -> float:
    return float(evaluate_map(_doc(url, name), gt)["ape_rmse"])


def test_manual_links_are_switchable_like_loop_closures() -> None:
    assert LinkKind.MANUAL in SWITCHABLE_KINDS and LinkKind.ODOMETRY not in SWITCHABLE_KINDS


def test_a_consistent_manual_link_closes_the_loop_that_views_never_matched(
    lap: tuple[Path, Trajectory], tmp_path: Path
) -> None:
    """Must happen: the link stays on, the map settles on it, APE falls (0.674 m, the odometry's, to 0.177 m)."""
    url, gt = _copy(lap, tmp_path), lap[1]
    before = _ape(url, "blind", gt)
    stated = _stated(url, gt, "blind", LAP_START, LAP_END)
    with open_database(url) as db:
        outcome = link_experiences(db, LinkRequest("blind", LAP_START, LAP_END, transform=stated, author="ops"))  # type: ignore[arg-type]
    assert outcome.active and outcome.misfit_m < 0.05 and outcome.map_name == "blind" and outcome.link == 86
    after = _ape(url, "blind", gt)
    assert before == pytest.approx(0.674, abs=0.01)
    assert after < 0.5 * before
    doc = _doc(url, "blind")
    manual = [link for link in doc["links"] if link["kind"] == "manual"]
    assert [(link["from"], link["to"], link.get("active", True)) for link in manual] == [(0, 69, True)]
    with open_database(url) as db, db.read() as conn:
        (listed,) = manual_links(conn=conn, map_id=get_map(conn=conn, name="blind").id)
    assert (listed.from_id, listed.to_id, listed.active, listed.author, listed.event) == (0, 69, True, "ops", 1)
    assert listed.transform == pytest.approx(stated)


def test_a_contradicting_manual_link_is_flagged_and_bends_nothing(lap: tuple[Path, Trajectory], tmp_path: Path) -> None:
    """Must not happen: a link 20 m off pulls nothing; it is kept switched off, reported, counted by the health."""
    url, gt = _copy(lap, tmp_path), lap[1]
    before_doc = _doc(url, "blind")
    before = _ape(url, "blind", gt)
    stated = list(_stated(url, gt, "blind", LAP_START, LAP_END))
    stated[0] += 20.0
    result = cli_json("link", "--db", url, "--map", "blind", "--from", "0", "--to", "69", "--author", "ops",
                      "--transform", ",".join(repr(v) for v in stated))  # fmt: skip
    assert (result["active"], result["flagged"], result["kind"]) == (False, True, "manual")
    assert result["misfit_m"] == pytest.approx(20.0, abs=1.5) and "contradicts the map" in result["reason"]
    assert _ape(url, "blind", gt) == pytest.approx(before, abs=1e-6)
    after_doc = _doc(url, "blind")
    moved = [math.dist((a["x"], a["y"]), (b["x"], b["y"]))
             for a, b in zip(before_doc["experiences"], after_doc["experiences"], strict=True)]  # fmt: skip
    assert max(moved) < 1e-6
    assert [(x["kind"], x.get("active", True)) for x in after_doc["links"][-1:]] == [("manual", False)]
    health = cli_json("maps", "--db", url)["maps"][0]["health"]
    assert health["switched_off"] == 1
    with open_database(url) as db:
        export_map(db, name="blind", fmt="g2o", out=tmp_path / "blind.g2o")
        streamed = (tmp_path / "blind.g2o").read_text(encoding="utf-8")
        assert streamed == g2o_text(load_map(db, name="blind").snapshot, planar=True)
    assert streamed.splitlines()[-2].startswith("# inactive EDGE_SE2 0 69 ") and streamed.endswith("\n# manual 0 69\n")


@pytest.mark.usefixtures("db_url")
def test_undo_restores_the_map_bit_for_bit(lap: tuple[Path, Trajectory], db_url: str, tmp_path: Path) -> None:  # noqa: F811
    """The link is a merge event: ``unmerge`` restores every array (a second undo refused); ``redo`` gives back the
    linked map bit for bit, from the archive the unmerge kept of it."""
    directory = lap[0].parent
    pipeline.process_into_store(directory / "single.bag", BLIND, db_url=db_url, map_name="blind")
    with open_database(db_url) as db:
        before = load_map(db, name="blind").snapshot
        outcome = link_experiences(db, LinkRequest("blind", LAP_START, LAP_END, author="ops"))  # the same place
        linked = load_map(db, name="blind").snapshot
        assert not np.array_equal(linked["em_pose"], before["em_pose"])
        assert cli_json("unmerge", "--db", db_url, "--event", str(outcome.event_id))["maps"] == ["blind"]
        assert_same_arrays(before, load_map(db, name="blind").snapshot)
        with pytest.raises(ConflictError, match="undone already"):
            unmerge(db, event_id=outcome.event_id)
        with db.read() as conn:
            assert manual_links(conn=conn, map_id=get_map(conn=conn, name="blind").id) == []
        redo_merge(db, event_id=outcome.event_id)
        assert_same_arrays(linked, load_map(db, name="blind").snapshot)
        with db.read() as conn:
            assert len(manual_links(conn=conn, map_id=get_map(conn=conn, name="blind").id)) == 1


def test_unknown_experiences_and_bad_transforms_are_refused_in_one_line(
    lap: tuple[Path, Trajectory], tmp_path: Path
) -> None:
    url = _copy(lap, tmp_path)
    for argv, message in (
        (["--from", "0", "--to", "87"], "ERROR: experience 87 does not exist in map 'blind' (it has 87)"),
        (["--from", "0", "--to", "0"], "ERROR: cannot link experience 0 to itself"),
        (["--from", "0", "--to", "5", "--transform", "1,2"], "ERROR: --transform takes four finite numbers"),
        (["--from", "0", "--to", "5", "--transform", "nan,0,0,0"], "ERROR: --transform takes four finite numbers"),
        (["--from", "0", "--to", "5", "--transform", "2e8,0,0,0"], "ERROR: link transform dx must be finite"),
        (["--from", "0", "--to", "5", "--to-map", "nowhere"], "ERROR: no map named 'nowhere'"),
    ):
        code, err = cli_code("link", "--db", url, "--map", "blind", *argv)
        assert code == 2 and len(err.strip().splitlines()) == 1 and err.startswith(message), (argv, err)
    assert cli_json("link", "--db", url, "--map", "blind", "--from", "0", "--to", "69")["active"]  # the same place
    code, err = cli_code("link", "--db", url, "--map", "blind", "--from", "69", "--to", "0")
    assert code == 1 and err.strip() == "ERROR: experiences 69 and 0 are linked already"


def _token(url: str, scope: str, label: str | None = None) -> tuple[int, dict[str, str]]:
    with open_database(url) as db, db.write() as conn:
        token, record = create_token(conn=conn, scope=scope, label=label)
    return record.id, {"Authorization": f"Bearer {token}"}


def test_the_rest_api_adds_lists_and_undoes_manual_links(lap: tuple[Path, Trajectory], tmp_path: Path) -> None:
    url = _copy(lap, tmp_path)
    write_id, write = _token(url, "write", "alice")
    _read_id, read = _token(url, "read")
    body = {"from": 0, "to": 69}
    with TestClient(create_app(Settings(db_url=url, upload_dir=tmp_path / "uploads"))) as client:
        assert client.post("/v1/maps/blind/links", json=body).status_code == 401
        assert client.post("/v1/maps/blind/links", json=body, headers=read).status_code == 403
        missing = client.post("/v1/maps/blind/links", json={"from": 0, "to": 500}, headers=write)
        assert missing.status_code == 404 and missing.json()["detail"].startswith("experience 500 does not exist")
        assert client.post("/v1/maps/nowhere/links", json=body, headers=write).status_code == 404
        assert client.post("/v1/maps/blind/links", json={"from": -1, "to": 3}, headers=write).status_code == 422
        far = {**body, "transform": {"dx": 2e8}}
        assert client.post("/v1/maps/blind/links", json=far, headers=write).status_code == 400
        added = client.post("/v1/maps/blind/links", json=body, headers=write)
        assert added.status_code == 201, added.text
        answer = added.json()
        assert (answer["active"], answer["author"], answer["from"], answer["to"]) == (
            True, f"token {write_id} (alice)", 0, 69)  # fmt: skip
        assert client.post("/v1/maps/blind/links", json=body, headers=write).status_code == 409
        (listed,) = client.get("/v1/maps/blind/links", headers=read).json()["links"]
        assert (listed["event"], listed["author"], listed["active"], listed["kind"]) == (
            answer["event"], answer["author"], True, "manual")  # fmt: skip
        events = client.get("/v1/merges", headers=read).json()["merges"]
        assert [(e["id"], e["mode"], e["status"]) for e in events] == [(answer["event"], "manual", "applied")]
        assert (events[0]["link"]["author"], events[0]["link"]["active"]) == (answer["author"], True)
        undone = client.post(f"/v1/merges/{answer['event']}/undo", headers=write)
        assert undone.status_code == 200 and undone.json()["status"] == "undone"
        assert client.get("/v1/maps/blind/links", headers=read).json()["links"] == []


@pytest.fixture(scope="module")
def tour(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Trajectory]:
    """The Virtual Tour's two sessions stored as two maps ``one`` and ``two`` (never merged), and their ground truth."""
    directory = tmp_path_factory.mktemp("tour")
    simulate_once("ellipse", directory, scale=0.5, params={"session2_laps": 1.25, "single_laps": 0.6},
                  only=["session1", "session2"])  # fmt: skip
    url = f"sqlite:///{directory / 'two.db'}"
    for log, name in (("session1", "one"), ("session2", "two")):
        pipeline.process_into_store(directory / f"{log}.bag", preset("circle"), db_url=url, map_name=name, merge=False)
    g1, g2 = read_tum(directory / "session1.tum"), read_tum(directory / "session2.tum")
    gt = Trajectory(np.concatenate([g1.stamps_s, g2.stamps_s]), np.concatenate([g1.positions_xyz, g2.positions_xyz]),
                    np.concatenate([g1.quat_xyzw, g2.quat_xyzw])).sorted()  # fmt: skip
    return directory / "two.db", gt


def _nearest_pair(url: str, gt: Trajectory) -> tuple[int, int]:
    """The experiences of map ``two`` and map ``one`` nearest each other in the world."""
    two, one = _doc(url, "two")["experiences"], _doc(url, "one")["experiences"]
    p2 = _true_poses(gt, [e["stamp"] for e in two])
    p1 = _true_poses(gt, [e["stamp"] for e in one])
    gaps = np.linalg.norm(p2[:, None, :2] - p1[None, :, :2], axis=2)
    a, b = np.unravel_index(int(np.argmin(gaps)), gaps.shape)
    return int(a), int(b)


@pytest.mark.parametrize("error_m", [0.0, 20.0], ids=["stated-truly", "stated-20m-off"])
def test_linking_two_maps_merges_them_through_the_link(
    tour: tuple[Path, Trajectory], tmp_path: Path, error_m: float
) -> None:
    """B (``one``) is placed by the stated transform: told truly the merged map fits the world (APE 0.36 m); told
    20 m off it is 20 m off (one link cannot be contradicted). Either way one event, undone bit for bit."""
    shutil.copy(tour[0], tmp_path / "two.db")
    url, gt = f"sqlite:///{tmp_path / 'two.db'}", tour[1]
    a, b = _nearest_pair(url, gt)
    stated = list(_stated(url, gt, "two", a, b, doc_b="one"))
    stated[1] += error_m
    with open_database(url) as db:
        before = {n: load_map(db, name=n).snapshot for n in ("one", "two")}
        outcome = link_experiences(db, LinkRequest("two", a, b, to_map="one", transform=tuple(stated), author="ops"))  # type: ignore[arg-type]
    assert outcome.map_name == "one" and outcome.merged == ["two"] and outcome.active  # the oldest map's name
    doc = _doc(url, "one")
    assert sorted(s["name"] for s in doc["sessions"]) == ["session1", "session2"] and len(doc["experiences"]) == 59
    (manual,) = [link for link in doc["links"] if link["kind"] == "manual"]
    assert (manual["from"], manual["to"]) == (outcome.from_id, outcome.to_id)
    poses = {e["id"]: np.array([e["x"], e["y"], e["z"], e["yaw"]]) for e in doc["experiences"]}
    placed = compose(poses[outcome.from_id], np.asarray(stated))
    assert np.allclose(poses[outcome.to_id][:3], placed[:3], atol=1e-6)
    ape = float(evaluate_map(doc, gt)["ape_rmse"])
    assert ape < 0.5 if error_m == 0.0 else ape > 5.0
    with open_database(url) as db:
        unmerge(db, event_id=outcome.event_id)
        for name, snapshot in before.items():
            assert_same_arrays(snapshot, load_map(db, name=name).snapshot)


def test_without_the_robust_check_a_link_goes_in_unchecked_and_says_so(
    lap: tuple[Path, Trajectory], tmp_path: Path
) -> None:
    """The check is what flags: a map whose parameters switch it off (``exp_robust``) takes the 20 m link, is bent
    by it (APE up several-fold), and the answer says ``checked: false`` rather than pass it off as checked."""
    url, gt = f"sqlite:///{tmp_path / 'unchecked.db'}", lap[1]
    log = lap[0].parent / "single.bag"
    pipeline.process_into_store(log, BLIND.replace(exp_robust=False), db_url=url, map_name="blind")
    before = _ape(url, "blind", gt)
    stated = list(_stated(url, gt, "blind", LAP_START, LAP_END))
    stated[0] += 20.0
    with open_database(url) as db:
        outcome = link_experiences(db, LinkRequest("blind", LAP_START, LAP_END, transform=tuple(stated), author="ops"))  # type: ignore[arg-type]
    assert (outcome.checked, outcome.active, outcome.as_dict()["flagged"]) == (False, True, False)
    assert _ape(url, "blind", gt) > 3 * before

"""``mapserver maps`` and ``export --format json|tum|png`` of stored maps."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from mapserver.cli import main
from mapserver.formats import read_map_json, read_tum
from mapserver.store import Database, NewSession, save_map
from tests.mapserver.store.conftest import drive_engine, small_params


@pytest.fixture
def stored(db: Database) -> dict[str, np.ndarray]:
    params = small_params()
    a = drive_engine(params, laps=2.2, seed=3)
    save_map(db, name="two", params=params, snapshot=a.snapshot(), sessions=[
        NewSession(name="monday", log_name="monday.bag", log_sha256="a" * 64, topics={}, params=params.to_dict(),
                   frames_processed=a.frames)])  # fmt: skip
    return a.snapshot()


def test_maps_lists_counts(db_url: str, stored: dict[str, np.ndarray], capsys) -> None:  # type: ignore[no-untyped-def]
    assert main(["maps", "--db", db_url, "--json"]) == 0
    listed = json.loads(capsys.readouterr().out.splitlines()[-1])
    health = listed["maps"][0].pop("health")
    assert listed == {
        "maps": [{"name": "two", "sessions": 1, "templates": stored["lv_templates"].shape[0],
                  "experiences": stored["em_pose"].shape[0], "links": stored["em_link_from"].shape[0],
                  "merges": {"applied": 0, "undone": 0, "rejected": 0, "unverified": 0}}]
    }  # fmt: skip
    assert health["links"] == stored["em_link_from"].shape[0] and health["switched_off"] == 0
    assert main(["maps", "--db", db_url]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].endswith("merges (rejected, unverified)")
    assert lines[1].split()[:2] == ["two", "1"] and lines[1].split()[-3:] == ["0", "(0,", "0)"]


def test_export_json_follows_the_contract(db_url: str, stored, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    out = tmp_path / "map.json"
    assert main(["export", "--db", db_url, "--map", "two", "--format", "json", "--out", str(out)]) == 0
    doc = read_map_json(out)
    assert doc["sessions"] == [{"name": "monday", "log_sha256": "a" * 64, "frames": 176}]
    assert doc["templates"] == stored["lv_templates"].shape[0]
    assert [e["id"] for e in doc["experiences"]] == list(range(stored["em_pose"].shape[0]))
    assert {e["session"] for e in doc["experiences"]} == {"monday"}
    e5 = doc["experiences"][5]
    x, y, z, yaw = stored["em_pose"][5]
    assert (e5["x"], e5["y"], e5["z"], e5["yaw"]) == (x, y, z, yaw)
    assert (e5["qz"], e5["qw"]) == (np.sin(yaw / 2), np.cos(yaw / 2))
    kinds = [link["kind"] for link in doc["links"]]
    assert kinds == [("odometry", "loop")[k] for k in stored["em_link_kind"].tolist()] and "loop" in kinds
    assert doc["params"] == small_params().to_dict()


def test_export_tum_and_png(db_url: str, stored, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    tum = tmp_path / "poses.tum"
    assert main(["export", "--db", db_url, "--map", "two", "--format", "tum", "--out", str(tum)]) == 0
    trajectory = read_tum(tum)
    order = np.argsort(stored["em_stamp"], kind="stable")
    assert np.array_equal(trajectory.stamps_s, np.round(stored["em_stamp"][order], 9))
    assert np.array_equal(trajectory.positions_xyz, stored["em_pose"][order, :3])
    png = tmp_path / "graph.png"
    assert main(["export", "--db", db_url, "--map", "two", "--format", "png", "--out", str(png)]) == 0
    image = cv2.imread(str(png))
    assert image is not None and image.shape == (800, 800, 3)
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 10  # a plot, not a blank canvas


def test_unknown_map_and_bad_output_are_exit_2(db_url: str, stored, tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    assert main(["export", "--db", db_url, "--map", "nope", "--format", "json", "--out", str(tmp_path / "x")]) == 2
    assert capsys.readouterr().err.strip() == "ERROR: no map named 'nope' in this database"
    assert main(["export", "--db", db_url, "--map", "two", "--format", "tum", "--out", str(tmp_path / "no/x")]) == 2
    assert "output directory does not exist" in capsys.readouterr().err


def test_paged_experiences_and_the_graph_match_the_snapshot(db: Database, stored) -> None:  # type: ignore[no-untyped-def]
    from mapserver.store import get_map
    from mapserver.store.queries import load_graph, page_experiences

    with db.read() as conn:
        map_id = get_map(conn=conn, name="two").id
        page, total = page_experiences(conn=conn, map_id=map_id, offset=10, limit=5)
        graph = load_graph(conn=conn, map_id=map_id)
    assert total == stored["em_pose"].shape[0]
    assert [e["id"] for e in page] == [10, 11, 12, 13, 14]
    assert [e["x"] for e in page] == stored["em_pose"][10:15, 0].tolist()
    assert {e["session"] for e in page} == {"monday"}
    assert np.array_equal(graph.poses, stored["em_pose"])
    assert np.array_equal(graph.link_to, stored["em_link_to"])
    assert np.array_equal(graph.link_kind, stored["em_link_kind"])

"""Standard outputs of a stored map: g2o (and back as the map's poses) and CSV tables."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapserver.cli import main
from mapserver.formats.csv import links_csv
from mapserver.formats.g2o import g2o_text, read_g2o_vertices
from mapserver.store import load_map, open_database
from tests.mapserver.store.test_import import LINKS, TX, TY, small_params, write_save_dir


def _stored_map(tmp_path: Path, db_url: str) -> str:
    """Import the 4-experience hand-written save as map 'm' (links LINKS of test_import)."""
    config = tmp_path / "params.yaml"
    values = small_params().replace(template_x_size=TX, template_y_size=TY).to_dict()
    config.write_text("".join(f"{k}: {v}\n" for k, v in values.items()))
    argv = ["import", str(write_save_dir(tmp_path / "save")), "--db", db_url, "--format", "multisession-ratslam",
            "--map", "m", "--config", str(config)]  # fmt: skip
    assert main(argv) == 0
    return "m"


def _export(db_url: str, fmt: str, out: Path) -> None:
    assert main(["export", "--db", db_url, "--map", "m", "--format", fmt, "--out", str(out)]) == 0


def test_g2o_export_writes_vertices_edges_and_the_stated_information(tmp_path: Path, db_url: str) -> None:
    _stored_map(tmp_path, db_url)
    _export(db_url, "g2o", tmp_path / "m.g2o")
    lines = (tmp_path / "m.g2o").read_text().splitlines()
    vertices = [line.split() for line in lines if line.startswith("VERTEX_SE2")]
    edges = [line.split() for line in lines if line.startswith("EDGE_SE2")]
    assert lines[-1] == "FIX 0" and len(vertices) == 4 and len(edges) == 4
    # vertex 2 is the save's experience 2: (2.0, 0.5), yaw 0.3
    assert [float(v) for v in vertices[2][1:]] == [2, 2.0, 0.5, 0.3]
    # edge 2 is link (d 1.2, heading 2.5, facing -0.2) from 2 to 3: measurement (d cos h, d sin h, facing)
    d, heading, facing, to, frm, _dt = LINKS[2]
    edge = [float(v) for v in edges[2][1:]]
    assert edge[:5] == [frm, to, d * math.cos(heading), d * math.sin(heading), facing]
    # information: σ_xy = 0.02 + 0.05·1.2 = 0.08 m, σ_yaw = 0.01 + 0.05·1.2 = 0.07 rad, diagonal
    assert edge[5:] == pytest.approx([1 / 0.08**2, 0.0, 0.0, 1 / 0.08**2, 0.0, 1 / 0.07**2], rel=1e-12)


def test_g2o_import_sets_the_maps_poses(tmp_path: Path, db_url: str, capsys: pytest.CaptureFixture[str]) -> None:
    _stored_map(tmp_path, db_url)
    _export(db_url, "g2o", tmp_path / "m.g2o")
    with open_database(db_url) as db:
        before = load_map(db, name="m")
    # an "optimiser": every vertex turned by 90° about the origin and moved 1 m in x
    out = []
    for line in (tmp_path / "m.g2o").read_text().splitlines():
        f = line.split()
        if f[0] == "VERTEX_SE2":
            x, y, yaw = (float(v) for v in f[2:])
            out.append(f"VERTEX_SE2 {f[1]} {1.0 - y!r} {x!r} {yaw + math.pi / 2!r}")
        else:
            out.append(line)
    (tmp_path / "opt.g2o").write_text("\n".join(out) + "\n")
    argv = ["import", str(tmp_path / "opt.g2o"), "--db", db_url, "--format", "g2o", "--map", "m", "--json"]
    assert main(argv) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["experiences"] == 4 and result["map"] == "m"
    with open_database(db_url) as db:
        after = load_map(db, name="m")
    old, new = before.snapshot["em_pose"], after.snapshot["em_pose"]
    assert np.array_equal(new[:, 0], 1.0 - old[:, 1]) and np.array_equal(new[:, 1], old[:, 0])
    assert np.array_equal(new[:, 3], old[:, 3] + math.pi / 2) and np.array_equal(new[:, 2], old[:, 2])
    # everything but the poses is kept
    for key in ("em_link_transform", "em_link_from", "lv_templates", "em_stamp", "pc_activity"):
        assert np.array_equal(after.snapshot[key], before.snapshot[key])
    assert after.meta.map.version == before.meta.map.version + 1
    # round trip: exporting again gives the file's vertices back
    _export(db_url, "g2o", tmp_path / "again.g2o")
    assert (
        read_g2o_vertices(tmp_path / "again.g2o").poses.tolist()
        == read_g2o_vertices(tmp_path / "opt.g2o").poses.tolist()
    )


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t.replace("VERTEX_SE2 3 ", "VERTEX_SE2 7 "), "lacks vertex 3"),
        (lambda t: t + "VERTEX_SE2 4 0 0 0\n", "has vertex 4, which is no experience"),
        (lambda t: t.replace("VERTEX_SE2 1 1.0 ", "VERTEX_SE2 1 one "), "is not a number"),
        (lambda t: "".join(f"VERTEX_SE3:QUAT {i} 0 0 0 0.2 0 0 0.98\n" for i in range(4)), "tilted by 0.4"),
    ],
)
def test_g2o_import_refuses_files_that_are_not_this_maps_poses(
    tmp_path: Path, db_url: str, capsys, edit, message
) -> None:  # type: ignore[no-untyped-def]
    _stored_map(tmp_path, db_url)
    _export(db_url, "g2o", tmp_path / "m.g2o")
    (tmp_path / "bad.g2o").write_text(edit((tmp_path / "m.g2o").read_text()))
    with open_database(db_url) as db:
        version = load_map(db, name="m").meta.map.version
    argv = ["import", str(tmp_path / "bad.g2o"), "--db", db_url, "--format", "g2o", "--map", "m"]
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    with open_database(db_url) as db:
        assert load_map(db, name="m").meta.map.version == version  # nothing written


def test_csv_export_matches_the_map_json(tmp_path: Path, db_url: str) -> None:
    _stored_map(tmp_path, db_url)
    _export(db_url, "csv", tmp_path / "m.csv")
    _export(db_url, "json", tmp_path / "m.json")
    doc = json.loads((tmp_path / "m.json").read_text())
    with (tmp_path / "m.csv").open(newline="") as handle:
        experiences = list(csv.DictReader(handle))
    with (tmp_path / "m.links.csv").open(newline="") as handle:
        links = list(csv.DictReader(handle))
    assert len(experiences) == len(doc["experiences"]) == 4 and len(links) == len(doc["links"]) == 4
    for row, exp in zip(experiences, doc["experiences"], strict=True):
        assert row["session"] == exp["session"] == "m"
        for key in ("id", "template", "stamp", "x", "y", "z", "yaw", "qx", "qy", "qz", "qw"):
            assert float(row[key]) == exp[key]
    for row, link in zip(links, doc["links"], strict=True):
        assert (int(row["from"]), int(row["to"]), row["kind"]) == (link["from"], link["to"], link["kind"])
        assert [float(row[k]) for k in ("dx", "dy", "dz", "dyaw")] == link["transform"]
        assert (float(row["dt"]), float(row["distance"])) == (link["dt"], link["distance"])
    assert {row.get("active", "true") for row in links} == {"true"}  # none switched off (core.robust)
    assert all(link.get("active", True) for link in doc["links"])


def _graph(n: int, active: list[bool] | None = None) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(n)
    snap = {
        "em_pose": rng.uniform(-5, 5, (n, 4)),
        "em_link_from": np.arange(n - 1),
        "em_link_to": np.arange(1, n),
        "em_link_transform": rng.uniform(-1, 1, (n - 1, 4)),
        "em_link_distance": rng.uniform(0, 2, n - 1),
        "em_link_dt": np.ones(n - 1),
        "em_link_kind": np.zeros(n - 1, dtype=np.int8),
    }
    if active is not None:
        snap["em_link_active"] = np.asarray(active)
    return snap


def test_inactive_links_pass_through(tmp_path: Path) -> None:
    snap = _graph(4, [True, False, True])
    text = g2o_text(snap, planar=True)
    assert sum(line.startswith("EDGE_SE2") for line in text.splitlines()) == 2
    assert sum(line.startswith("# inactive EDGE_SE2 1 2 ") for line in text.splitlines()) == 1
    rows = list(csv.DictReader(links_csv(snap).splitlines()))
    assert [r["active"] for r in rows] == ["true", "false", "true"]
    assert sum(line.startswith("EDGE_SE2") for line in g2o_text(_graph(4), planar=True).splitlines()) == 3


@settings(max_examples=40, deadline=None)
@given(n=st.integers(2, 12), planar=st.booleans(), yaw=st.floats(-math.pi + 1e-6, math.pi - 1e-6))
def test_vertices_read_back_as_written(
    tmp_path_factory: pytest.TempPathFactory, n: int, planar: bool, yaw: float
) -> None:
    snap = _graph(n)
    snap["em_pose"][0, 3] = yaw
    if planar:
        snap["em_pose"][:, 2] = 0.0
    path = tmp_path_factory.mktemp("g2o") / "g.g2o"
    path.write_text(g2o_text(snap, planar=planar))
    read = read_g2o_vertices(path)
    assert read.kind == ("VERTEX_SE2" if planar else "VERTEX_SE3:QUAT") and read.ids.tolist() == list(range(n))
    expected = snap["em_pose"].copy()
    if not planar:  # yaw comes back through the quaternion, wrapped into (-π, π]
        expected[:, 3] = np.arctan2(np.sin(expected[:, 3]), np.cos(expected[:, 3]))
        assert read.max_tilt_rad == 0.0
    assert np.allclose(read.poses, expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("planar", [True, False])
def test_gtsam_reads_every_active_edge_of_an_export_with_switched_off_links(tmp_path: Path, planar: bool) -> None:
    """GTSAM's ``readG2o`` (PyPI package) stops at the first line it does not know: switched-off links come last.

    A 12-experience chain whose links 2 and 7 are switched off, plus two closures: GTSAM must read all 11
    vertices' poses and the 11 active edges (must happen), and none of the two switched off (must not).
    """
    import gtsam  # a dev dependency (pyproject.toml), installed by `make install`
    n = 12
    snap = _graph(n, [k not in (2, 7) for k in range(n - 1)])
    snap["em_link_from"] = np.concatenate([snap["em_link_from"], [0, 3]])
    snap["em_link_to"] = np.concatenate([snap["em_link_to"], [9, 11]])
    for key, extra in (("em_link_transform", np.zeros((2, 4))), ("em_link_distance", np.ones(2)),
                       ("em_link_active", np.ones(2, dtype=bool))):  # fmt: skip
        snap[key] = np.concatenate([snap[key], extra])
    path = tmp_path / "map.g2o"
    path.write_text(g2o_text(snap, planar=planar))
    graph, initial = gtsam.readG2o(str(path), not planar)
    assert initial.size() == n
    edges = sorted(
        (min(f.keys()), max(f.keys())) for f in (graph.at(i) for i in range(graph.size())) if len(f.keys()) == 2
    )
    expected = sorted({(k, k + 1) for k in range(n - 1)} - {(2, 3), (7, 8)} | {(0, 9), (3, 11)})
    assert edges == expected
    text = path.read_text().splitlines()
    assert text.index("FIX 0") < min(i for i, line in enumerate(text) if line.startswith("# inactive"))

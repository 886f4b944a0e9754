"""The viewer's API: viewport graph decimation, nearest node, node details, evidence, merges with undo/redo."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapserver.api.viewdata import ViewGraph, decimate, nearest, parse_bbox
from mapserver.cli.demo import build_demo
from mapserver.errors import InputError
from tests.mapserver.api.conftest import Api
from tests.mapserver.api.graphmaps import store_graph_map


def graph_of(xy: np.ndarray, links: list[tuple[int, int, int]], sessions: np.ndarray | None = None) -> ViewGraph:
    n = xy.shape[0]
    arr = np.asarray(links, dtype=np.int64).reshape(-1, 3)
    return ViewGraph(
        map_id=1, version=1, poses=np.column_stack([xy, np.zeros(n), np.zeros(n)]),
        session=np.zeros(n, dtype=np.int64) if sessions is None else sessions, template=np.arange(n),
        stamp=np.arange(n, dtype=np.float64), session_names=["a", "b", "c"], link_from=arr[:, 0], link_to=arr[:, 1],
        link_kind=arr[:, 2], link_active=np.ones(arr.shape[0], bool), link_dt=np.ones(arr.shape[0]),
        link_distance=np.ones(arr.shape[0]),
    )  # fmt: skip


def test_a_box_with_few_nodes_returns_exactly_those_inside_and_their_links() -> None:
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [5.0, 5.0]])
    g = graph_of(xy, [(0, 1, 0), (1, 2, 0), (2, 3, 1), (0, 2, 1)])
    out = decimate(g, bbox=(-0.5, -0.5, 2.5, 0.5), max_nodes=10)
    assert out["nodes"]["id"] == [0, 1, 2] and not out["decimated"] and out["in_view"] == 3
    pairs = {(out["nodes"]["id"][a], out["nodes"]["id"][b], k)
             for a, b, k in zip(out["links"]["a"], out["links"]["b"], out["links"]["kind"], strict=True)}  # fmt: skip
    assert pairs == {(0, 1, 0), (1, 2, 0), (0, 2, 1)}  # the link to node 3 (outside) is left out
    assert out["bounds"] == [0.0, 0.0, 5.0, 5.0] and out["total"] == 4


def test_a_dense_box_keeps_the_lowest_id_of_each_grid_cell() -> None:
    # a 100 x 100 lattice of unit spacing, ids row by row; 100 nodes allowed -> a 10 x 10 grid of 9.9 m cells
    ii, jj = np.meshgrid(np.arange(100), np.arange(100), indexing="ij")
    xy = np.column_stack([jj.ravel(), ii.ravel()]).astype(np.float64)
    chain = [(k, k + 1, 0) for k in range(xy.shape[0] - 1)]
    out = decimate(graph_of(xy, chain), bbox=None, max_nodes=100)
    assert out["decimated"] and out["in_view"] == 10_000 and out["cell"] == pytest.approx(9.9)
    expected = {}
    for k, (x, y) in enumerate(xy.tolist()):  # independent: the first id met in each cell
        cell = (min(int(y / 9.9), 9), min(int(x / 9.9), 9))
        expected.setdefault(cell, k)
    assert sorted(out["nodes"]["id"]) == sorted(expected.values()) and len(out["nodes"]["id"]) == 100
    rep = {k: expected[(min(int(y / 9.9), 9), min(int(x / 9.9), 9))] for k, (x, y) in enumerate(xy.tolist())}
    ids = out["nodes"]["id"]
    want = {tuple(sorted((rep[a], rep[b]))) for a, b, _k in chain if rep[a] != rep[b]}
    got = {tuple(sorted((ids[a], ids[b]))) for a, b in zip(out["links"]["a"], out["links"]["b"], strict=True)}
    assert got == want


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 400), max_nodes=st.integers(1, 60), seed=st.integers(0, 2**16), n_sessions=st.integers(1, 3)
)
def test_decimation_never_exceeds_the_budget_and_keeps_every_occupied_cell(
    n: int, max_nodes: int, seed: int, n_sessions: int
) -> None:
    rng = np.random.default_rng(seed)
    xy = rng.normal(0, 10, size=(n, 2))
    sessions = rng.integers(0, n_sessions, size=n)
    out = decimate(graph_of(xy, [], sessions), bbox=None, max_nodes=max_nodes)
    kept = out["nodes"]["id"]
    present = len(set(sessions.tolist()))  # every session keeps a node, even past a budget smaller than that
    assert len(kept) <= max(max_nodes, present) and len(set(kept)) == len(kept)
    if not out["decimated"]:
        assert sorted(kept) == list(range(n))
    else:  # every session present in the map is still drawn
        assert set(np.asarray(out["nodes"]["session"]).tolist()) == set(sessions.tolist())


def test_bad_bbox_is_an_input_error_and_nearest_is_the_closest() -> None:
    for text in ("1,2,3", "0,0,0,1", "a,b,c,d", "0,0,nan,1"):
        with pytest.raises(InputError):
            parse_bbox(text)
    assert parse_bbox("0,1,2,3") == (0.0, 1.0, 2.0, 3.0)
    g = graph_of(np.array([[0.0, 0.0], [3.0, 4.0], [10.0, 0.0]]), [])
    assert nearest(g, 2.9, 3.0) == 1 and nearest(g, 7.0, 0.0) == 2


def test_graph_nearest_and_node_endpoints(api: Api) -> None:
    xy = np.array([[0.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [1.0, 1.0, 0.5, 0.0]])
    store_graph_map(api.db_url, "tri", xy, [(0, 1, 1.0, 1.0), (1, 2, 2.0, 1.0)])
    assert api.client.get("/v1/maps/tri/graph").status_code == 401  # the API's token rules
    body = api.client.get("/v1/maps/tri/graph", headers=api.read).json()
    assert body["nodes"]["id"] == [0, 1, 2] and body["links"]["kind"] == [0, 0] and body["sessions"] == ["tri"]
    side = api.client.get("/v1/maps/tri/graph", params={"view": "xz"}, headers=api.read).json()
    assert side["nodes"]["y"] == [0.0, 0.0, 0.5]  # the side view draws z
    bad = api.client.get("/v1/maps/tri/graph", params={"bbox": "1,1,0,0"}, headers=api.read)
    assert bad.status_code == 400 and "bbox" in bad.json()["detail"]
    assert api.client.get("/v1/maps/nope/graph", headers=api.read).status_code == 404
    near = api.client.get("/v1/maps/tri/nearest", params={"x": 0.9, "y": 0.8}, headers=api.read).json()
    assert near["id"] == 2 and near["distance"] == pytest.approx(np.hypot(0.1, 0.2))
    node = api.client.get("/v1/maps/tri/experiences/1", headers=api.read).json()
    assert [(lk["from"], lk["to"], lk["kind"]) for lk in node["links"]] == [(0, 1, "odometry"), (1, 2, "odometry")]
    assert node["session"] == "tri" and node["template"] == 0 and node["template_new"] is False
    assert api.client.get("/v1/maps/tri/experiences/3", headers=api.read).status_code == 404
    none = api.client.get("/v1/maps/tri/experiences/1/evidence", headers=api.read)
    assert none.status_code == 404 and "evidence" in none.json()["detail"]


def test_evidence_of_a_processed_session_is_its_stored_jpeg(api: Api, strip_log: Path) -> None:
    import cv2

    from mapserver.store import get_map, open_database
    from mapserver.store.evidence import get_evidence

    job = api.upload(strip_log, preset="irat", map="strip").json()["job"]
    assert api.wait(job)["status"] == "done"
    got = api.client.get("/v1/maps/strip/experiences/2/evidence", headers=api.read)
    assert got.status_code == 200 and got.headers["content-type"] == "image/jpeg"
    with open_database(api.db_url) as db, db.read() as conn:
        stored = get_evidence(conn=conn, map_id=get_map(conn=conn, name="strip").id, experience=2)
    assert got.content == stored.data
    image = cv2.imdecode(np.frombuffer(got.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.shape[:2] == (stored.height, stored.width)


@pytest.mark.slow
def test_merges_listed_with_places_and_undone_and_redone_with_a_write_token(make_api: Any) -> None:
    api = make_api()
    build_demo(api.db_url)
    merges = api.client.get("/v1/merges", params={"map": "demo"}, headers=api.read).json()["merges"]
    (event,) = merges
    assert event["status"] == "applied" and event["sessions"] == {"demo-a": "target", "demo-b": "source"}
    sessions_marked = {n["session"] for place in event["places"] for n in place["nodes"]}
    assert sessions_marked == {"demo-a", "demo-b"}  # each matched place is found in both sessions
    url = f"/v1/merges/{event['id']}"
    assert api.client.post(url + "/undo").status_code == 401
    assert api.client.post(url + "/undo", headers=api.read).status_code == 403
    undone = api.client.post(url + "/undo", headers=api.write)
    assert undone.status_code == 200 and undone.json()["status"] == "undone"
    assert len(api.client.get("/v1/maps/demo", headers=api.read).json()["sessions"]) == 1
    assert api.client.post(url + "/undo", headers=api.write).status_code == 409
    redone = api.client.post(url + "/redo", headers=api.write)
    assert redone.status_code == 200 and redone.json()["status"] == "applied"
    assert len(api.client.get("/v1/maps/demo", headers=api.read).json()["sessions"]) == 2
    assert api.client.get("/v1/merges/999", headers=api.read).status_code == 404


def test_the_viewer_and_the_report_style_exactly_the_link_kinds_the_api_names() -> None:
    """viewer.js keys its styles by kind name (the API sends the names, ``kinds``); no kind goes unstyled."""
    from mapserver.formats import LINK_KIND_NAMES
    from mapserver.report import LINK_STYLE

    script = (Path(__file__).resolve().parents[3] / "mapserver/api/viewer/static/viewer.js").read_text()
    block = re.search(r"const LINK_STYLES = \{(.*?)\n\};", script, re.S)
    assert block is not None
    styled = set(re.findall(r"^\s*(\w+):", block.group(1), re.M))
    assert styled == {*LINK_KIND_NAMES, "inactive"}
    assert set(LINK_STYLE) == set(LINK_KIND_NAMES)

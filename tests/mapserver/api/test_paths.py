"""Path queries: 404 unknown node, 409 no path, 422 bad params, and the per-map graph cache."""

from __future__ import annotations

import numpy as np

from tests.mapserver.api.conftest import Api
from tests.mapserver.api.graphmaps import store_graph_map


def _two_islands(api: Api, name: str = "islands") -> None:
    # 0-1-2-3 is a square with a slow diagonal 0-2; 4-5 is a separate island
    poses = np.array([[0, 0, 0, 0], [1, 0, 0, 0], [1, 1, 0, 0], [0, 1, 0, 0], [5, 5, 0, 0], [6, 5, 0, 0]], float)
    links = [(0, 1, 1.0, 1.0), (1, 2, 1.0, 1.0), (2, 3, 1.0, 1.0), (3, 0, 1.0, 1.0), (0, 2, 5.0, 1.5),
             (4, 5, 2.0, 1.0)]  # fmt: skip
    store_graph_map(api.db_url, name, poses, links)


def test_path_costs_by_time_and_distance(api: Api) -> None:
    _two_islands(api)
    by_time = api.client.get("/v1/maps/islands/path?from=0&to=2", headers=api.read).json()
    assert by_time["cost"] == 2.0 and by_time["nodes"] in ([0, 1, 2], [0, 3, 2])
    by_distance = api.client.get("/v1/maps/islands/path?from=0&to=2&weight=distance", headers=api.read).json()
    assert by_distance == {"nodes": [0, 2], "poses": [{"x": 0.0, "y": 0.0, "z": 0.0, "yaw": 0.0},
                                                      {"x": 1.0, "y": 1.0, "z": 0.0, "yaw": 0.0}],
                           "cost": 1.5, "weight": "distance"}  # fmt: skip
    reverse = api.client.get("/v1/maps/islands/path?from=5&to=4", headers=api.read).json()
    assert reverse["nodes"] == [5, 4] and reverse["cost"] == 2.0
    same = api.client.get("/v1/maps/islands/path?from=3&to=3", headers=api.read).json()
    assert same["nodes"] == [3] and same["cost"] == 0.0


def test_path_errors(api: Api) -> None:
    _two_islands(api)
    no_path = api.client.get("/v1/maps/islands/path?from=0&to=5", headers=api.read)
    assert no_path.status_code == 409
    assert no_path.json() == {"detail": "no path from experience 0 to 5 in map 'islands': they are not connected"}
    unknown = api.client.get("/v1/maps/islands/path?from=0&to=6", headers=api.read)
    assert unknown.status_code == 404
    assert unknown.json() == {"detail": "map 'islands' has no experience 6 (ids are 0..5)"}
    no_map = api.client.get("/v1/maps/nowhere/path?from=0&to=1", headers=api.read)
    assert no_map.status_code == 404 and "no map named 'nowhere'" in no_map.json()["detail"]
    for query in ("from=-1&to=2", "from=a&to=2", "to=2", "from=0&to=1&weight=fuel", "from=0&to=99999999999999999999"):
        bad = api.client.get(f"/v1/maps/islands/path?{query}", headers=api.read)
        assert bad.status_code == 422, query
        assert isinstance(bad.json()["detail"], str) and bad.json()["detail"]
    page = api.client.get("/v1/maps/islands/experiences?limit=0", headers=api.read)
    assert page.status_code == 422 and "limit" in page.json()["detail"]


def test_graph_is_cached_until_the_map_changes(api: Api) -> None:
    _two_islands(api)
    cache = api.client.app.state.services.graphs  # type: ignore[attr-defined]
    for _ in range(5):
        assert api.client.get("/v1/maps/islands/path?from=0&to=2", headers=api.read).status_code == 200
    assert cache.builds == 1
    # a new write of the map (version + 1) connects the islands: the next query sees it
    from mapserver.store import load_map, open_database, save_map

    with open_database(api.db_url) as db:
        content = load_map(db, name="islands")
        snap = dict(content.snapshot)
        for key, value in (("em_link_from", 2), ("em_link_to", 4)):
            snap[key] = np.append(snap[key], value)
        snap["em_link_transform"] = np.vstack([snap["em_link_transform"], np.zeros((1, 4))])
        snap["em_link_dt"] = np.append(snap["em_link_dt"], 10.0)
        snap["em_link_distance"] = np.append(snap["em_link_distance"], 6.0)
        snap["em_link_kind"] = np.append(snap["em_link_kind"], np.int8(3))
        sessions = [s.id for s in content.meta.sessions]
        save_map(db, name="islands", params=content.params, snapshot=snap, sessions=sessions,
                 expected_version=content.meta.map.version)  # fmt: skip
    joined = api.client.get("/v1/maps/islands/path?from=0&to=5", headers=api.read).json()
    assert joined["nodes"] in ([0, 1, 2, 4, 5], [0, 3, 2, 4, 5]) and joined["cost"] == 2.0 + 10.0 + 2.0
    assert cache.builds == 2


def test_the_cache_keeps_the_most_recently_queried_maps_and_shares_one_graph_between_threads(api: Api) -> None:
    """Capacity 2, maps a, b, c: queries a, b, a, c evict b (queried least recently) and keep a and c; a query of
    b builds it again (evicting a). Eight threads querying c at once all get the one cached graph."""
    from concurrent.futures import ThreadPoolExecutor

    from mapserver.api.graphs import GraphCache
    from mapserver.store import open_database

    poses = np.zeros((3, 4))
    for name, dt in (("a", 1.0), ("b", 2.0), ("c", 3.0)):
        store_graph_map(api.db_url, name, poses, [(0, 1, dt, 1.0), (1, 2, dt, 1.0)])
    with open_database(api.db_url) as db:
        cache = GraphCache(db, capacity=2)
        for name in ("a", "b", "a", "c"):
            assert cache.shortest_path(name, 0, 2, "time").cost == 2 * {"a": 1.0, "b": 2.0, "c": 3.0}[name]
        assert cache.builds == 3
        assert cache.current("a") is not None and cache.current("c") is not None  # must still be cached
        assert cache.current("b") is None  # must not: evicted
        assert cache.get("b").graph.shortest_path(2, 0).cost == 4.0 and cache.builds == 4
        assert cache.current("a") is None and cache.current("c") is not None
        with ThreadPoolExecutor(8) as pool:
            entries = list(pool.map(lambda _: cache.get("c"), range(32)))
        assert cache.builds == 4 and all(entry is entries[0] for entry in entries)

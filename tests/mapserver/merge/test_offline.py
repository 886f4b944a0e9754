"""Offline merge of two stored maps: search, confirmation, refusal."""

from __future__ import annotations

import numpy as np
import pytest

from core.angles import wrap_angle
from core.se3 import compose
from mapserver.errors import MergeError
from mapserver.merge import StoredMap, find_match, merge_maps
from tests.mapserver.merge.sessions import PARAMS, map_stretch, true_alignment
from tests.mapserver.merge.world import LoopWorld

WORLD = LoopWorld(perimeter=40.0)


@pytest.fixture(scope="module")
def maps() -> tuple[StoredMap, StoredMap]:
    """A: arcs 0–25; B: arcs 15–40. They share arcs 15–25."""
    return map_stretch(WORLD, 0.0, 25.0, 1), map_stretch(WORLD, 15.0, 25.0, 2)


def test_map_a_merges_into_map_b(maps: tuple[StoredMap, StoredMap]) -> None:
    a, b = maps
    engine, record = merge_maps(a, b)
    assert record.confirmations >= PARAMS.merge_confirm
    truth = true_alignment(WORLD, 15.0, 0.0)
    t = np.asarray(record.transform)
    assert float(np.linalg.norm(t[:3] - truth[:3])) < 0.3 and abs(float(wrap_angle(t[3] - truth[3]))) < 0.05
    n_a, n_b = (int(np.shape(m.state["em_pose"])[0]) for m in (a, b))
    identified = int(np.count_nonzero(record.experience_map < n_b))
    assert identified >= 1
    assert engine.experience_count == n_b + n_a - identified == record.experiences
    assert engine.template_count == record.templates < n_a + int(np.shape(b.state["lv_means"])[0])
    # B's ids come first (settling moves them by centimetres at most); A is in B's frame: its places land
    # on the world's
    assert np.array_equal(engine.map.templates[:n_b], b.state["em_template"])
    assert np.abs(engine.map.poses[:n_b, :3] - b.state["em_pose"][:, :3]).max() < 0.05
    kept = record.experience_map >= n_b
    a_world = compose(WORLD.pose(0.0), a.state["em_pose"][kept])
    merged_world = compose(WORLD.pose(15.0), engine.map.poses[record.experience_map[kept]])
    assert np.abs(merged_world[:, :2] - a_world[:, :2]).max() < 0.3
    # one connected map: a path from A's first place to B's last
    path = engine.shortest_path(int(record.experience_map[0]), n_b - 1, "distance")
    assert path.nodes[0] == int(record.experience_map[0]) and path.nodes[-1] == n_b - 1
    assert record.merge_links.size >= 1


def test_maps_without_common_places_are_refused() -> None:
    a = map_stretch(WORLD, 0.0, 8.0, 1)
    b = map_stretch(WORLD, 20.0, 8.0, 2)
    with pytest.raises(MergeError, match="no template of map 1 matches map 2"):
        merge_maps(a, b)


def test_a_run_shorter_than_k_is_refused(maps: tuple[StoredMap, StoredMap]) -> None:
    a, b = maps
    with pytest.raises(MergeError, match=r"longest agreeing run has \d+ \(needs 200"):
        find_match(a, b, confirm=200)


def test_incompatible_parameters_are_refused(maps: tuple[StoredMap, StoredMap]) -> None:
    a, b = maps
    with pytest.raises(MergeError, match="template sizes differ"):
        merge_maps(StoredMap(1, PARAMS.replace(template_x_size=16), a.state), b)

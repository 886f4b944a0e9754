"""Offline merges of ``sdr-htm`` maps: view cells compared by their codes, re-expressed in the loaded cortex."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.angles import wrap_angle
from core.config import preset
from core.engine import Engine
from core.neocortex.viewcells import NeocortexViewCells
from mapserver.errors import MergeError, NoConfirmedMatchError
from mapserver.merge.cortex import translate_offline
from mapserver.merge.engines import StoredMap, merge_snapshots
from mapserver.merge.offline_evidence import confirmed_offline_match
from mapserver.merge.offline_views import code_rows, offline_incompatibility, partial_views
from mapserver.merge.places import template_places
from tests.worlds import StripWorld

SDR = preset("irat").replace(frontend="sdr-htm", merge_sdr_min_overlap=0.45)
"""The engine tests' small sdr-htm setup, its code gate calibrated to the strip world's imagery: a lap at another
speed sees each place 0–0.25 m off (2 of 64 columns), and its best code overlaps 0.52–1.0; another world's
best overlaps 0.36 at most (the simulator's true places: 0.67–0.77 at the 10th percentile, the default 0.68)."""


def _map(world: StripWorld, key: int, laps: float = 1.0, speed: float = 1.0) -> StoredMap:
    engine = Engine(SDR, origin=key)
    for frame in world.drive(laps=laps, speed=speed):
        engine.step(*frame)
    engine.settle()
    return StoredMap(key, SDR, engine.snapshot())


@pytest.fixture(scope="module")
def maps() -> tuple[StoredMap, StoredMap, StoredMap]:
    """0.6 of a lap of one strip world; a lap of it at another speed (other frames of its places); another world."""
    return _map(StripWorld(seed=3), 1, 0.6), _map(StripWorld(seed=3), 2, speed=1.3), _map(StripWorld(seed=11), 3)


def test_sdr_maps_merge_offline_by_their_codes_and_not_without_them(maps: tuple[StoredMap, ...]) -> None:
    a, b, _ = maps
    assert offline_incompatibility(a, b) is None  # must still: codes on both sides
    no_codes = StoredMap(4, SDR, {**b.state, "lv_sdr": np.zeros_like(b.state["lv_sdr"])})
    assert "keeps no view-cell codes" in (offline_incompatibility(a, no_codes) or "")  # stored before lv_sdr
    no_places = StoredMap(7, SDR, {k: v for k, v in b.state.items() if not k.startswith("lv_place")})
    assert "keeps no view-cell places" in (offline_incompatibility(no_places, a) or "")  # stored before lv_place
    lvc = StoredMap(5, preset("irat"), a.state)
    assert "front-ends differ" in (offline_incompatibility(a, lvc) or "")
    other = StoredMap(6, SDR.replace(sp_columns=1024), b.state)
    assert "sp_columns" in (offline_incompatibility(a, other) or "")
    with pytest.raises(MergeError, match="keeps no view-cell codes"):
        confirmed_offline_match(no_codes, a, None)


def test_a_view_cell_is_offered_as_its_code_at_its_place(maps: tuple[StoredMap, ...]) -> None:
    _, b, _ = maps
    views = partial_views(b)
    codes = np.asarray(b.state["lv_sdr"])
    assert views.views.shape == (codes.shape[0], 1, SDR.sv_tm_topk + codes.shape[1])
    assert (views.views[:, 0, : SDR.sv_tm_topk] == -1).all()  # no descriptor: read by codes only
    np.testing.assert_array_equal(views.views[:, 0, SDR.sv_tm_topk :], codes)
    np.testing.assert_array_equal(code_rows(codes[:2], 3)[1, 0], [-1, -1, -1, *codes[1]])
    places, experiences = template_places(b.state)
    np.testing.assert_array_equal(views.experiences, experiences)
    placed = experiences >= 0
    np.testing.assert_array_equal(views.poses[placed], places[placed])
    np.testing.assert_array_equal(views.packets[placed], np.asarray(b.state["em_pc"])[experiences[placed]])


def test_the_partials_view_cells_get_the_loaded_cortexs_reading_of_their_codes(maps: tuple[StoredMap, ...]) -> None:
    """Each of B's view cells gets the descriptor A's cortex (learning off) reads at its code, codes read in B's
    creation order; the merged map continues in A's cortex, its learnt state untouched."""
    a, b, _ = maps
    translated, cortex = translate_offline(SDR, a.state, b.state)
    reading = NeocortexViewCells.restore(SDR, a.state)
    rows = np.asarray(translated["lv_templates"]).reshape(-1, SDR.sv_tm_topk)
    for template, code in enumerate(np.asarray(b.state["lv_sdr"])):
        d = reading.read(np.zeros(0), code=code)
        np.testing.assert_array_equal(rows[template][: d.size], d)
        assert (rows[template][d.size :] == -1).all() and translated["lv_means"][template] == d.size
    assert (np.asarray(translated["lv_means"]) > 0).mean() > 0.9  # nearly every view cell reads as something
    for key in ("nc_sp_permanence", "nc_sp_active_duty", "nc_tm_seg_cell", "nc_tm_syn_perm"):
        np.testing.assert_array_equal(cortex[key], a.state[key])  # nothing learnt
    np.testing.assert_array_equal(translated["lv_sdr"], b.state["lv_sdr"])  # the codes stay the partial's


def test_an_sdr_map_merges_offline_into_its_own_place_and_not_into_another_world(maps: tuple[StoredMap, ...]) -> None:
    a, b, c = maps
    match, evidence = confirmed_offline_match(b, a, None)  # must happen: the same places, other frames
    assert evidence.passed and evidence.misses <= 0.1 * evidence.hits
    engine, record = merge_snapshots(a, b, match)
    t = np.asarray(record.transform)
    assert math.hypot(t[0], t[1]) < 0.5 and abs(float(wrap_angle(t[3]))) < 0.1  # both laps start at one pose
    n_a = int(np.shape(a.state["lv_means"])[0])
    assert engine.template_count == record.templates > n_a
    merged = engine.snapshot()
    np.testing.assert_array_equal(np.asarray(merged["lv_sdr"])[:n_a], a.state["lv_sdr"])
    assert (np.asarray(merged["lv_means"])[n_a:] > 0).all()  # B's new view cells carry A-cortex prototypes
    with pytest.raises(NoConfirmedMatchError):  # must not: another world
        confirmed_offline_match(c, a, None)

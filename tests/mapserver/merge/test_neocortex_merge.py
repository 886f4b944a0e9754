"""Merging maps of the sdr-htm front-end: a stored map's own cortex reads the session (issue 17 part 5)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from core.config import ConfigError, preset
from core.engine import Engine
from mapserver.merge.cortex import CortexReader
from mapserver.merge.places import merged_template_places, template_places
from mapserver.merge.snapshot import params_incompatibility
from tests.worlds import StripWorld

SDR = preset("irat").replace(frontend="sdr-htm")  # the engine tests' small sdr-htm setup


def test_sdr_maps_merge_online_with_the_same_cortex_structure_and_lvc_maps_still_merge() -> None:
    sdr = preset("poseidon-sdr")
    assert params_incompatibility(preset("poseidon"), preset("poseidon")) is None  # must still merge
    assert "front-ends differ" in (params_incompatibility(preset("poseidon"), sdr) or "")
    assert params_incompatibility(sdr, sdr, reads_frames=True) is None
    assert "merge only online" in (params_incompatibility(sdr, sdr) or "")  # offline: no frames to read
    assert "sp_columns" in (params_incompatibility(sdr, sdr.replace(sp_columns=1024), reads_frames=True) or "")
    assert params_incompatibility(sdr, sdr.replace(sv_min_intersection=8), reads_frames=True) is None  # a gate


def test_the_miss_weight_is_the_front_ends_own_unless_given() -> None:
    assert preset("circle").miss_weight == 2.0  # LVC: mapserver.merge.hypotheses.MISS_WEIGHT
    p1, p0 = 0.4, 0.02
    wald = math.log((1 - p0) / (1 - p1)) / math.log(p1 / p0)
    assert preset("poseidon-sdr").miss_weight == pytest.approx(wald, abs=0.01)
    assert preset("poseidon-sdr").replace(merge_miss_weight=0.5).miss_weight == 0.5
    with pytest.raises(ConfigError, match="merge_miss_weight"):
        preset("circle").replace(merge_miss_weight=0.0)


def _session(world: StripWorld, laps: float) -> tuple[Engine, list]:  # type: ignore[type-arg]
    frames = list(world.drive(laps=laps))
    engine = Engine(SDR)
    for frame in frames:
        engine.step(*frame)
    return engine, frames


def test_a_stored_maps_cortex_recognises_its_place_in_another_session_and_not_another_world() -> None:
    engine, frames = _session(StripWorld(seed=3), laps=1.0)
    state = engine.snapshot()
    reader = CortexReader(SDR, state, row=0)
    found = []
    for frame in frames:  # the same route driven again by another session
        view = reader.read(frame[0])[None, :]
        found.append(reader.match(view, 0.0)[0])
    found_arr = np.asarray(found)
    creator = np.cumsum([0, *[1] * (len(frames) - 1)])  # lap 1 made about one view cell per frame
    recognised = found_arr >= 0
    assert recognised.mean() >= 0.5  # must happen: the map's own cells, read without learning
    near = np.abs(found_arr[recognised] - creator[recognised]) <= 3
    assert near.mean() >= 0.9  # and at the right place of the sequence
    assert np.array_equal(engine.snapshot()["nc_tm_seg_cell"], state["nc_tm_seg_cell"])  # the map did not learn
    other = CortexReader(SDR, state, row=0)
    strangers = [other.match(other.read(f[0])[None, :], 0.0)[0] for f in StripWorld(seed=11).drive(laps=0.5)]
    assert sum(u >= 0 for u in strangers) <= 0.05 * len(strangers)  # must not: another world


def test_a_reading_is_reported_like_a_template_match() -> None:
    engine, frames = _session(StripWorld(seed=3), laps=0.4)
    reader = CortexReader(SDR, engine.snapshot(), row=1)
    view = np.full((2, SDR.sv_tm_topk), -1, dtype=np.int64)
    u, error, rel = reader.match(view, 0.0, limit=0.1)  # row 1 empty: nothing read
    assert (u, error, rel) == (-1, math.inf, 0.0)
    for frame in frames[:12]:
        view[1] = reader.read(frame[0])
    u, error, rel = reader.match(view, 0.0, limit=0.1)
    assert u >= 0 and 0.0 <= error <= 0.1 and rel == 0.0  # accepted: error = limit · (1 − R)
    assert reader.match_among(view, 0.0, np.array([u]), limit=0.1)[0] == u
    assert reader.match_among(view, 0.0, np.array([], dtype=np.int64))[0] == -1
    reader.remember(4, view)
    reader.remember(4, np.zeros_like(view))  # the first reading of a view cell is kept
    partial = {"lv_means": np.zeros(6), "lv_templates": np.zeros((6, 1, SDR.sv_tm_topk), np.float32)}
    moved = reader.translated(partial)
    np.testing.assert_array_equal(moved["lv_templates"][4, 0], view[1].astype(np.float32))
    assert moved["lv_means"][4] == (view[1] >= 0).sum() and moved["lv_means"][0] == 0  # 0: never read
    assert set(reader.cortex()) >= {"nc_sp_permanence", "nc_tm_seg_cell", "nc_history"}


def test_a_view_cells_place_is_its_experience_plus_the_offset() -> None:
    state = {
        "em_pose": np.array([[0.0, 0.0, 0.0, 0.0], [10.0, 0.0, 1.0, 1.0]]),
        "lv_means": np.zeros(4),
        "lv_place": np.array([0, 1, -1]),  # template 3 predates the key: no place
        "lv_place_offset": np.array([[1.0, 2.0, 0.0, 0.5], [0.0, -1.0, 0.5, 3.0], [0.0, 0.0, 0.0, 0.0]]),
    }
    poses, anchors = template_places(state)
    np.testing.assert_allclose(poses[:2], [[1.0, 2.0, 0.0, 0.5], [10.0, -1.0, 1.5, 3.0]])
    assert np.isnan(poses[2:]).all() and anchors.tolist() == [0, 1, -1, -1]


def test_a_merge_renumbers_the_partial_places_and_turns_their_offsets() -> None:
    loaded = {"lv_means": np.zeros(2), "lv_place": np.array([0, -1]), "lv_place_offset": np.ones((2, 4))}
    partial = {
        "lv_means": np.zeros(3),
        "lv_place": np.array([0, 1, -1]),
        "lv_place_offset": np.array([[9.0, 9.0, 9.0, 9.0], [1.0, 0.0, 0.3, 0.2], [0.0, 0.0, 0.0, 0.0]]),
    }
    record = SimpleNamespace(template_map=np.array([0, 2, 3]), template_offset=2,  # partial 0 identified
                             experience_map=np.array([5, 6]), transform=(4.0, 0.0, 0.0, math.pi / 2))
    merged = merged_template_places(loaded, partial, record)  # type: ignore[arg-type]
    assert merged["lv_place"].tolist() == [0, -1, 6, -1]
    np.testing.assert_allclose(merged["lv_place_offset"][:2], np.ones((2, 4)))
    np.testing.assert_allclose(merged["lv_place_offset"][2], [0.0, 1.0, 0.3, 0.2 + math.pi / 2], atol=1e-12)


def test_the_engine_records_where_each_view_cell_was_made_and_restores_it() -> None:
    engine, _ = _session(StripWorld(seed=3), laps=0.5)
    state = engine.snapshot()
    assert state["lv_place"].shape == (engine.template_count,)
    assert state["lv_place_offset"].shape == (engine.template_count, 4)
    made = state["lv_place"][state["lv_place"] >= 0]
    assert made.size >= 0.9 * engine.template_count and made.max() < engine.experience_count
    assert np.all(np.diff(made) >= 0)  # made in order along the route: the current experience only advances
    again = Engine.restore(SDR, state)
    np.testing.assert_array_equal(again.snapshot()["lv_place_offset"], state["lv_place_offset"])
    older = {k: v for k, v in state.items() if k not in ("lv_place", "lv_place_offset")}
    assert (Engine.restore(SDR, older).snapshot()["lv_place"] == -1).all()  # maps stored before the key

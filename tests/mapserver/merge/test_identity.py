"""Row identities through merges, and resuming the online driver from its exported state."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core import Engine
from mapserver.errors import MergeError
from mapserver.merge import OnlineMerger, StoredMap
from mapserver.merge.identity import RowIdentities, next_index_from_table
from mapserver.merge.online import MergerState
from mapserver.merge.record import MergeRecord
from tests.mapserver.merge.sessions import PARAMS, map_stretch
from tests.mapserver.merge.world import LoopWorld

WORLD = LoopWorld(perimeter=40.0)


def _record(tmap: list[int], emap: list[int], t_offset: int, e_offset: int) -> MergeRecord:
    return MergeRecord(
        stored_template=0, stored_experience=0, partial_template=0, partial_pose=(0.0, 0.0, 0.0, 0.0),
        relative_rad=0.0, confirmations=3, lattice_source=(0.0, 0.0, 0.0), lattice_target=(0.0, 0.0, 0.0),
        lattice_offset=(0.0, 0.0, 0.0), heading_offset_rad=0.0, lattice_shifted=True, transform=(0.0, 0.0, 0.0, 0.0),
        template_offset=t_offset, experience_offset=e_offset, link_offset=0,
        template_map=np.asarray(tmap, dtype=np.int64), experience_map=np.asarray(emap, dtype=np.int64),
        merge_links=np.zeros(0, dtype=np.int64),
    )  # fmt: skip


def test_new_rows_are_numbered_in_creation_order_and_identified_ones_leave_gaps() -> None:
    loaded = RowIdentities.from_arrays([1, 1, 1], [0, 1, 2], [1, 1], [0, 1])
    partial = RowIdentities()
    partial.extend(4, 3, tag=0)
    # partial template 2 and experience 1 are identified with loaded rows: they leave the map
    merged = RowIdentities.merged(loaded, partial, _record([3, 4, 1, 5], [2, 0, 3], 3, 2))
    assert merged.template_arrays()[0].tolist() == [1, 1, 1, 0, 0, 0]
    assert merged.template_arrays()[1].tolist() == [0, 1, 2, 0, 1, 3]
    assert merged.experience_arrays()[1].tolist() == [0, 1, 0, 2]
    merged.extend(7, 5, tag=0)  # rows made after the merge never reuse index 2 (template) or 1 (experience)
    assert merged.template_arrays()[1].tolist()[-1] == 4 and merged.experience_arrays()[1].tolist()[-1] == 3
    assert next_index_from_table(merged.retagged({0: 9}).next_table()) == {1: (3, 2), 9: (5, 4)}


def test_identities_refuse_what_a_merge_did_not_do() -> None:
    loaded = RowIdentities.from_arrays([1], [0], [1], [0])
    partial = RowIdentities()
    partial.extend(2, 1, tag=0)
    with pytest.raises(MergeError, match="keeps in their order"):
        RowIdentities.merged(loaded, partial, _record([2, 1], [1], 1, 1))
    with pytest.raises(MergeError, match="loaded identities cover"):
        RowIdentities.merged(loaded, partial, _record([1, 2], [1], 2, 1))
    with pytest.raises(MergeError, match="fewer than"):
        partial.extend(1, 1, tag=0)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.booleans(), min_size=1, max_size=30), st.integers(0, 5))
def test_merged_identities_are_unique_and_keep_the_kept_rows(identified: list[bool], n_loaded: int) -> None:
    loaded = RowIdentities.from_arrays([7] * n_loaded, range(n_loaded), [], [])
    partial = RowIdentities()
    partial.extend(len(identified), 0, tag=0)
    kept = [i for i, x in enumerate(identified) if not (x and n_loaded)]
    tmap = [0 if (x and n_loaded) else -1 for x in identified]
    for rank, i in enumerate(kept):
        tmap[i] = n_loaded + rank
    merged = RowIdentities.merged(loaded, partial, _record(tmap, [], n_loaded, 0))
    sessions, indices = merged.template_arrays()
    assert len(set(zip(sessions.tolist(), indices.tolist(), strict=True))) == merged.templates == n_loaded + len(kept)
    assert indices[n_loaded:].tolist() == kept


def test_the_driver_resumed_from_its_exported_state_merges_as_one_run() -> None:
    stored = map_stretch(WORLD, 0.0, 20.0, 1)
    frames = WORLD.drive(24.0, 40.0, t0=1000.0)

    def run(split: int | None) -> list[tuple[int, tuple[float, ...]]]:
        engine = Engine(PARAMS, origin=9)
        driver = OnlineMerger([stored])
        events = []
        for i, (image, motion, stamp) in enumerate(frames):
            if i == split:  # stop here and continue from the stored states (engine snapshot + driver arrays)
                arrays = driver.export_state().to_arrays()
                engine = Engine.restore(PARAMS, engine.snapshot(), origin=9)
                driver = OnlineMerger([stored], resume=MergerState.from_arrays(arrays))
            frame = SimpleNamespace(image=image, motion=motion, stamp_ns=round(stamp * 1e9))
            result = engine.step(image, motion, frame.stamp_ns * 1e-9)
            event = driver.observe(engine, result, frame)
            if event is not None:
                engine = event.engine
                events.append((event.frame, event.record.transform))
        return events

    whole = run(None)
    assert len(whole) == 1
    confirming = whole[0][0]
    assert run(confirming - 1) == whole  # stopped while the winning hypothesis gathers its evidence
    assert run(confirming // 2) == whole
    state = MergerState(np.arange(4.0), (3,), {})
    assert MergerState.from_arrays(state.to_arrays()).absorbed == (3,)


def test_stored_maps_as_merge_candidates_keep_their_key() -> None:
    stored = StoredMap(5, PARAMS, map_stretch(WORLD, 0.0, 4.0, 5).state)
    assert OnlineMerger([stored]).candidates == [5]

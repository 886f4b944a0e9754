"""sdr-htm maps in the database: the HTM state, projection and prototypes survive a stop and resume exactly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.config import preset
from mapserver.processing import pipeline
from mapserver.store import load_map, open_database
from tests.mapserver.store.conftest import assert_same_arrays, write_loop_log

pytestmark = pytest.mark.slow

PARAMS = preset("irat").replace(
    frontend="sdr-htm", lsbh_bits=512, sp_columns=512, sp_potential_radius=150, sp_num_active_columns=12,
    tm_cells_per_column=8, sv_tm_topk=10, sv_min_intersection=8,
)


def test_stop_after_then_resume_equals_one_run(tmp_path: Path, db_url: str, make_url) -> None:  # type: ignore[no-untyped-def]
    log = write_loop_log(tmp_path / "loop.bag", laps=1.6)
    one_go = pipeline.process_into_store(log, PARAMS, db_url=db_url)
    assert one_go.loop_closures > 0  # the second lap is recognised by its SDR view cells
    split = make_url()
    first = pipeline.process_into_store(log, PARAMS, db_url=split, stop_after=60)
    assert first.frames_run == 60
    pipeline.process_into_store(log, PARAMS, db_url=split)
    with open_database(db_url) as a, open_database(split) as b:
        whole, resumed = load_map(a, name="loop"), load_map(b, name="loop")
    assert_same_arrays(whole.snapshot, resumed.snapshot)
    for key in ("nc_projection", "nc_sp_permanence", "nc_tm_syn_pre", "nc_tm_syn_perm", "nc_history"):
        assert key in whole.snapshot, key
    assert whole.snapshot["lv_templates"].shape[1:] == (1, PARAMS.sv_tm_topk)
    assert np.array_equal(whole.snapshot["lv_means"], np.sum(whole.snapshot["lv_templates"][:, 0] >= 0, axis=1))


def test_an_archive_keeps_sdr_prototypes_inline_since_a_merge_rewrites_their_rows(tmp_path: Path, db_url: str) -> None:
    """An archive references stored template rows by identity, shape and mean (templates are immutable); an
    ``sdr-htm`` view cell's row is rewritten when a merge re-expresses its prototype, usually at the same size,
    so an archive that referenced it would restore the merged map's prototype (an offline merge's unmerge would
    then restore the wrong one). Its archives keep every prototype inline and restore the map as archived."""
    from sqlalchemy import update

    from mapserver.store.archive import archive_map_state, load_archive
    from mapserver.store.models import Template

    log = write_loop_log(tmp_path / "loop.bag", laps=1.0)
    pipeline.process_into_store(log, PARAMS, db_url=db_url)
    with open_database(db_url) as db:
        stored = load_map(db, name="loop")
        with db.write() as conn:
            archive = archive_map_state(conn=conn, map_id=stored.meta.map.id)
            other = np.full(PARAMS.sv_tm_topk, 7.0, dtype="<f4").tobytes()  # another prototype of the same size
            conn.execute(update(Template).values(data=other))  # as a merge's re-expression rewrites the rows
        with db.read() as conn:
            restored = load_archive(conn=conn, archive_id=archive).snapshot
    np.testing.assert_array_equal(restored["lv_templates"], stored.snapshot["lv_templates"])

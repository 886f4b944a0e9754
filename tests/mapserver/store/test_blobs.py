"""Shared arrays (the sdr-htm projection) are stored once per database and read back bit for bit."""

from __future__ import annotations

import uuid

import numpy as np
import pytest
import sqlalchemy as sa

from core import Engine
from mapserver.store import Database, NewSession, load_map, save_map
from mapserver.store import blobs as blob_module
from mapserver.store.archive import archive_map_state, load_archive
from mapserver.store.errors import CorruptStateError
from mapserver.store.models import Blob, MapArchive, MapState
from tests.mapserver.store.conftest import assert_same_arrays, drive_engine, small_params


@pytest.fixture(scope="module")
def engine() -> Engine:
    return drive_engine(small_params(), laps=1.0)


def _projection(seed: int = 7) -> np.ndarray:
    """A float32 projection with the bits a copy could lose: −0.0, NaN payload, ±inf, subnormals."""
    values = np.random.default_rng(seed).standard_normal((512, 256)).astype(np.float32)  # 512 KiB
    values[0, :4] = [-0.0, np.inf, -np.inf, np.float32(1e-45)]
    values[1, 0] = np.frombuffer(np.uint32(0x7FC00123).tobytes(), dtype=np.float32)[0]
    return values


def _save(db: Database, engine: Engine, name: str, projection: np.ndarray) -> None:
    params = small_params()
    save_map(db, name=name, params=params, snapshot={**engine.snapshot(), "nc_projection": projection}, sessions=[
        NewSession(name=name, log_name=f"{name}.bag", log_sha256=uuid.uuid4().hex * 2, topics={},
                   params=params.to_dict(), frames_processed=engine.frames)])  # fmt: skip


def _sizes(db: Database) -> tuple[int, int, int]:
    with db.read() as conn:
        blobs = conn.execute(sa.select(sa.func.count()).select_from(Blob)).scalar_one()
        states = conn.execute(sa.select(sa.func.sum(sa.func.length(MapState.arrays)))).scalar_one() or 0
        archives = conn.execute(sa.select(sa.func.sum(sa.func.length(MapArchive.state)))).scalar_one() or 0
    return int(blobs), int(states), int(archives)


def test_a_projection_is_stored_once_and_every_state_reads_it_bit_for_bit(db: Database, engine: Engine) -> None:
    projection = _projection()
    _save(db, engine, "a", projection)
    _save(db, engine, "b", projection)
    with db.write() as conn:
        archive = archive_map_state(conn=conn, map_id=load_map(db, name="a").meta.map.id)
    blobs, states, archives = _sizes(db)
    assert blobs == 1
    assert states + archives < projection.nbytes / 4  # two states and an archive: no copy of it (one: 4 ×)
    for name in ("a", "b"):
        snapshot = load_map(db, name=name).snapshot
        assert snapshot["nc_projection"].tobytes() == projection.tobytes()
        expected = {**engine.snapshot(), "nc_projection": projection}
        assert_same_arrays(expected, snapshot, skip=("lv_origin", "em_origin"))
    with db.read() as conn:
        archived = load_archive(conn=conn, archive_id=archive).snapshot["nc_projection"]
    assert archived.dtype == np.float32 and archived.tobytes() == projection.tobytes()
    _save(db, engine, "c", _projection(seed=8))  # another projection: a second blob
    assert _sizes(db)[0] == 2


def test_a_state_written_with_its_own_copy_reads_as_before(
    db: Database, engine: Engine, monkeypatch: pytest.MonkeyPatch
) -> None:
    """States written before migration 0006 hold the array inline; they read exactly as states that share it."""
    projection = _projection()
    monkeypatch.setattr(blob_module, "SHARED_KEYS", ())
    _save(db, engine, "inline", projection)
    monkeypatch.undo()
    assert _sizes(db)[0] == 0
    _save(db, engine, "shared", projection)
    inline, shared = load_map(db, name="inline").snapshot, load_map(db, name="shared").snapshot
    assert inline["nc_projection"].tobytes() == shared["nc_projection"].tobytes() == projection.tobytes()


@pytest.mark.parametrize("damage", ["missing", "damaged"])
def test_a_missing_or_damaged_blob_is_a_clear_error(db: Database, engine: Engine, damage: str) -> None:
    _save(db, engine, "a", _projection())
    with db.write() as conn:
        if damage == "missing":
            conn.execute(sa.delete(Blob))
        else:
            conn.execute(sa.update(Blob).values(data=blob_module.npy_bytes(_projection(seed=9))))
    with pytest.raises(CorruptStateError, match=rf"map 'a': the shared array 'nc_projection' .* is {damage}"):
        load_map(db, name="a")


def test_storing_a_blob_twice_is_a_no_op(db: Database) -> None:
    """Two writers that store one projection at once: the second insert must neither fail nor duplicate it."""
    arrays = {"nc_projection": _projection(), "other": np.arange(3)}
    with db.write() as conn:
        first = blob_module.share_arrays(conn, arrays)
        second = blob_module.share_arrays(conn, arrays)
        assert conn.execute(sa.select(sa.func.count()).select_from(Blob)).scalar_one() == 1
        assert set(first) == {"__blob__.nc_projection", "other"}
        assert np.array_equal(first["__blob__.nc_projection"], second["__blob__.nc_projection"])
        back = blob_module.resolve_arrays(conn, first, "test")
    assert back["nc_projection"].tobytes() == arrays["nc_projection"].tobytes() and back["other"].tolist() == [0, 1, 2]


def test_a_database_of_revision_0005_upgrades_and_its_maps_read_as_before(
    db_url: str, engine: Engine, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A map written before the ``blobs`` table existed (its projection inline) reads the same after
    ``db upgrade``; writing it again moves the projection into a blob.

    Today's models name columns of later revisions, so the map is written as the code before 0006 wrote it (the
    projection inline) at the head revision, and the database is then taken down to 0005 (which keeps the map's
    rows and drops every later table and column) before the upgrade under test."""
    from mapserver.store import create_db_engine, upgrade
    from mapserver.store.migrate import HEAD_REVISION, downgrade

    projection = _projection()
    with Database(create_db_engine(db_url)) as old:
        assert upgrade(old) == HEAD_REVISION
        monkeypatch.setattr(blob_module, "SHARED_KEYS", ())  # what the code before 0006 wrote
        _save(old, engine, "old", projection)
        monkeypatch.undo()
        assert downgrade(old, "0005") == "0005"
        assert upgrade(old) == HEAD_REVISION
        before = load_map(old, name="old")
        assert before.snapshot["nc_projection"].tobytes() == projection.tobytes()
        assert _sizes(old)[0] == 0
        save_map(old, name="old", params=small_params(), snapshot=before.snapshot,
                 sessions=[s.id for s in before.meta.sessions], expected_version=before.meta.map.version)  # fmt: skip
        assert _sizes(old)[0] == 1
        assert load_map(old, name="old").snapshot["nc_projection"].tobytes() == projection.tobytes()

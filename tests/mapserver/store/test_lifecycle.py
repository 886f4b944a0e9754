"""A map's lifecycle (issue 65): delete (archive) and restore bit for bit, purge, rename; SQLite and PostgreSQL.

The atlas: map ``B`` built by a merge of ``A`` into it (one merge event, two archived states), and map ``C``
alone. Every refusal is paired with what must still happen: the map stays as it was, the other map is
untouched, the request that is allowed passes.
"""

from __future__ import annotations

import hashlib
from functools import cache
from typing import Any

import numpy as np
import pytest
import sqlalchemy as sa

from mapserver.errors import ConflictError, InputError
from mapserver.store import (
    Database,
    MapExistsError,
    StaleMapError,
    UnknownMapError,
    claim_map,
    create_map,
    drop_map,
    find_map,
    get_map,
    list_maps,
    load_map,
    save_map,
    write_map_state,
)
from mapserver.store.archive import archive_map_state
from mapserver.store.jobs import create_job
from mapserver.store.lifecycle import archive_map, purge_map, rename_map, restore_map
from mapserver.store.maps import list_map_params
from mapserver.store.merge_events import MergeEventSpec, get_merge_event, record_merge_event
from mapserver.store.models import Base, Job
from mapserver.store.queries import map_version
from mapserver.store.streams import open_export
from tests.mapserver.store.conftest import digest, drive_engine, row_counts, small_params
from tests.mapserver.store.test_archive import _concat, _session


@cache
def _snapshot(laps: float, seed: int) -> dict[str, np.ndarray]:
    """An engine's snapshot around the strip world (driven once per test run)."""
    return drive_engine(small_params(), laps=laps, seed=seed).snapshot()


def _atlas(db: Database) -> int:
    """Store ``B`` (``A`` merged into it: sessions a and b, one event) and ``C``; return the event id."""
    params = small_params()
    save_map(db, name="A", params=params, snapshot=_snapshot(0.6, 3), sessions=[_session("a")])
    save_map(db, name="B", params=params, snapshot=_snapshot(0.5, 5), sessions=[_session("b")])
    save_map(db, name="C", params=params, snapshot=_snapshot(0.4, 7), sessions=[_session("c")])
    a, b = load_map(db, name="A"), load_map(db, name="B")
    with db.write() as conn:
        event = record_merge_event(conn=conn, spec=MergeEventSpec(
            map_id=b.meta.map.id, map_name="B", mode="offline", confirmations=3, lattice_offset=[1.0, -2.0, 3.0],
            transform=(0.5, 0.25, 0.0, 0.0, 0.0, 0.0, 1.0), yaw=0.0, matches={"templates": []},
            target_sessions=[s.id for s in b.meta.sessions], source_sessions=[s.id for s in a.meta.sessions],
        ))  # fmt: skip
        archive_map_state(conn=conn, map_id=b.meta.map.id, event_id=event, role="target")
        archive_map_state(conn=conn, map_id=a.meta.map.id, event_id=event, role="source")
        drop_map(conn=conn, map_id=a.meta.map.id)
        write_map_state(
            conn=conn, map_id=b.meta.map.id, expected_version=b.meta.map.version, params=params,
            snapshot=_concat(b.snapshot, a.snapshot),
            session_ids=[s.id for s in (*b.meta.sessions, *a.meta.sessions)],
            template_index=np.concatenate([b.meta.template_index, a.meta.template_index]),
            experience_index=np.concatenate([b.meta.experience_index, a.meta.experience_index]),
        )  # fmt: skip
    return event


def _bytes(db: Database, name: str, fmt: str) -> bytes:
    """The map's export in ``fmt``, streamed from the store as ``GET .../export`` sends it."""
    stream = open_export(db, name=name, fmt=fmt)
    try:
        return b"".join(stream)
    finally:
        stream.close()


def _export(db: Database, name: str) -> str:
    """SHA-256 of the map's JSON and TUM exports."""
    return hashlib.sha256(_bytes(db, name, "json") + _bytes(db, name, "tum")).hexdigest()


def _state(db: Database, name: str) -> str:
    """SHA-256 of the map's loaded snapshot, parameters and row identities."""
    content = load_map(db, name=name)
    meta = content.meta
    h = hashlib.sha256(digest(content.snapshot).encode())
    h.update(repr(sorted(content.params.items())).encode())
    for array in (meta.template_index, meta.experience_index):
        h.update(np.ascontiguousarray(array).tobytes())
    h.update(repr([(s.id, s.name, s.status) for s in meta.sessions]).encode())
    return h.hexdigest()


def _rows(db: Database) -> str:
    """SHA-256 of every row of every table, in key order (the maps' ``archived_at`` left out)."""
    h = hashlib.sha256()
    with db.read() as conn:
        for name, table in sorted(Base.metadata.tables.items()):
            columns = [c for c in table.columns if not (name == "maps" and c.name == "archived_at")]
            query = sa.select(*columns).order_by(*table.primary_key.columns)
            for row in conn.execute(query):
                h.update(repr((name, tuple(row))).encode())
    return h.hexdigest()


def _fingerprint(db: Database, name: str) -> tuple[str, str, str]:
    return _export(db, name), _state(db, name), _rows(db)


def test_delete_then_restore_gives_the_same_map_bit_for_bit(db: Database) -> None:
    _atlas(db)
    before, other = _fingerprint(db, "B"), _export(db, "C")
    with db.write() as conn:
        archived = archive_map(conn=conn, name="B")
    assert archived.archived_at is not None
    # must not happen: B is found, listed, exported, offered as a merge candidate
    with db.read() as conn:
        assert find_map(conn=conn, name="B") is None and map_version(conn=conn, name="B") is None
        with pytest.raises(UnknownMapError, match="no map named 'B'"):
            get_map(conn=conn, name="B")
        assert [m.name for m in list_maps(conn=conn)] == ["C"]
        assert [p.name for p in list_map_params(conn=conn)] == ["C"]
        (listed,) = list_maps(conn=conn, archived=True)
        assert (listed.name, listed.sessions, listed.as_dict()["archived_at"]) == (
            "B", 2, archived.archived_at.isoformat())
    with pytest.raises(UnknownMapError):
        _export(db, "B")
    # must still happen: the other map is as it was; the archived map's rows are all there
    assert _export(db, "C") == other
    assert _rows(db) == before[2]
    with db.write() as conn:
        restored = restore_map(conn=conn, name="B")
    assert restored.archived_at is None and restored.id == archived.id
    assert _fingerprint(db, "B") == before
    with db.read() as conn:
        assert [m.name for m in list_maps(conn=conn)] == ["B", "C"] and list_maps(conn=conn, archived=True) == []


def test_refused_lifecycle_requests_leave_the_map_as_it_was(db: Database) -> None:
    _atlas(db)
    with db.write() as conn:
        job = create_job(conn=conn, upload_path="/x/b.bag", upload_name="b.bag", upload_sha256="0" * 64,
                         map_name="B", preset="irat", topics=None, options={})  # fmt: skip
    before = _fingerprint(db, "B")
    refusals: list[tuple[Any, str]] = [
        (lambda c: archive_map(conn=c, name="B"), f"job {job.id} is processing a log into map 'B'"),
        (lambda c: rename_map(conn=c, name="B", new_name="D"), f"job {job.id} is processing"),
        (lambda c: restore_map(conn=c, name="B"), "map 'B' is not archived"),
        (lambda c: purge_map(conn=c, name="B"), "map 'B' is not archived; delete it first"),
        (lambda c: archive_map(conn=c, name="nope"), "no map named 'nope'"),
        (lambda c: rename_map(conn=c, name="B", new_name="C"), "the name 'C' is held by another map"),
        (lambda c: rename_map(conn=c, name="B", new_name="a/b"), "invalid map name 'a/b'"),
    ]
    for call, message in refusals:
        with pytest.raises((ConflictError, UnknownMapError, InputError), match=message), db.write() as conn:
            call(conn)
    assert _fingerprint(db, "B") == before
    with db.write() as conn:  # the job ended: the same request passes
        conn.execute(sa.update(Job).where(Job.id == job.id).values(status="done"))
        archive_map(conn=conn, name="B")
    with pytest.raises(ConflictError, match="archived already"), db.write() as conn:
        archive_map(conn=conn, name="B")
    # a writer that read B before the delete (a session resuming in it) cannot write into it: it reads again
    record = load_map(db, name="C").meta.map
    with db.read() as conn:
        archived = find_map(conn=conn, name="B", archived=True)
    assert archived is not None
    with pytest.raises(StaleMapError, match="deleted \\(archived\\)"), db.write() as conn:
        claim_map(conn=conn, map_id=archived.id, expected_version=archived.version)
    with db.write() as conn:  # must still happen: a live map's write
        assert claim_map(conn=conn, map_id=record.id, expected_version=record.version) == record.version + 1
    with pytest.raises(ConflictError, match="restore it before you rename it"), db.write() as conn:
        rename_map(conn=conn, name="B", new_name="D")


def test_an_archived_map_holds_its_name_until_it_is_purged(db: Database) -> None:
    event = _atlas(db)
    other, counts = _export(db, "C"), row_counts(db)
    with db.write() as conn:
        archive_map(conn=conn, name="B")
    with pytest.raises(MapExistsError, match="held by an archived"), db.write() as conn:
        create_map(conn=conn, name="B", params={})
    with pytest.raises(MapExistsError, match="held by an archived"), db.write() as conn:
        rename_map(conn=conn, name="C", new_name="B")
    with db.write() as conn:
        outcome = purge_map(conn=conn, name="B")
    assert outcome.as_dict() == {"purged": "B", "sessions": 2, "merge_events": 1}
    after = row_counts(db)
    assert after["maps"] == counts["maps"] - 1 and after["sessions"] == counts["sessions"] - 2
    assert after["merge_events"] == after["map_archives"] == after["merge_event_sessions"] == 0
    with db.read() as conn:
        c_templates = load_map(db, name="C").snapshot["lv_templates"].shape[0]
        assert after["templates"] == c_templates  # only C's templates are left
        with pytest.raises(Exception, match=str(event)):
            get_merge_event(conn=conn, event_id=event)
        assert find_map(conn=conn, name="B", archived=None) is None
    assert _export(db, "C") == other  # must still happen: C untouched
    with db.write() as conn:  # the name is free again
        create_map(conn=conn, name="B", params={})


def test_rename_moves_the_map_and_its_merge_history_to_the_new_name(db: Database) -> None:
    event = _atlas(db)
    state, tables = _state(db, "B"), {fmt: _bytes(db, "B", fmt) for fmt in ("tum", "csv", "links.csv", "g2o")}
    with db.write() as conn:
        renamed = rename_map(conn=conn, name="B", new_name="D.v-2")
    assert renamed.name == "D.v-2"
    with db.read() as conn, pytest.raises(UnknownMapError):
        get_map(conn=conn, name="B")
    assert _state(db, "D.v-2") == state  # the same content under the new name
    assert {fmt: _bytes(db, "D.v-2", fmt) for fmt in tables} == tables
    with db.read() as conn:
        record = get_merge_event(conn=conn, event_id=event)
        archives = conn.execute(sa.text("SELECT role, map_name FROM map_archives ORDER BY id")).all()
    assert record.map_name == "D.v-2"
    assert [tuple(r) for r in archives] == [("target", "D.v-2"), ("source", "A")]  # A's archive keeps its name

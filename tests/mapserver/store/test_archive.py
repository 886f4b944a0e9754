"""Archives for unmerge (issue 5): a merge-like change is undone exactly; template pixels are not copied."""

from __future__ import annotations

import numpy as np
import pytest

from mapserver.errors import NotFoundError
from mapserver.store import Database, NewSession, drop_map, get_map, load_map, save_map, write_map_state
from mapserver.store.archive import (
    archive_map_state,
    archive_state,
    delete_archive,
    load_archive,
    restore_map_states,
    restore_progress,
)
from mapserver.store.merge_events import (
    MergeEventSpec,
    get_merge_event,
    list_merge_events,
    record_merge_event,
    set_merge_status,
)
from mapserver.store.models import MapArchive
from mapserver.store.sessions import cut_session, get_activations, get_session_progress, set_activations
from tests.mapserver.store.conftest import assert_same_arrays, drive_engine, row_counts, small_params


def _session(name: str) -> NewSession:
    params = small_params()
    return NewSession(name=name, log_name=name, log_sha256=name.ljust(64, "0"), topics={}, params=params.to_dict())


def _concat(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A crude 'merge': b's rows appended after a's, b's ids shifted (enough to exercise the store)."""
    n, e = a["lv_templates"].shape[0], a["em_pose"].shape[0]
    out = dict(a)
    for key in ("lv_templates", "lv_means", "lv_origin", "pc_link_coords", "pc_link_strength", "pc_link_decay",
                "em_pose", "em_pc", "em_stamp", "em_origin", "em_link_transform", "em_link_dt", "em_link_distance",
                "em_link_kind"):  # fmt: skip
        out[key] = np.concatenate([a[key], b[key]])
    out["pc_link_template"] = np.concatenate([a["pc_link_template"], b["pc_link_template"] + n])
    out["em_template"] = np.concatenate([a["em_template"], b["em_template"] + n])
    out["em_link_from"] = np.concatenate([a["em_link_from"], b["em_link_from"] + e])
    out["em_link_to"] = np.concatenate([a["em_link_to"], b["em_link_to"] + e])
    return out


def test_a_merge_is_undone_exactly_from_its_archives(db: Database) -> None:
    params = small_params()
    save_map(db, name="A", params=params, snapshot=drive_engine(params, laps=1.2, seed=3).snapshot(),
             sessions=[_session("a")])  # fmt: skip
    save_map(db, name="B", params=params, snapshot=drive_engine(params, laps=1.0, seed=5).snapshot(),
             sessions=[_session("b")])  # fmt: skip
    a, b = load_map(db, name="A"), load_map(db, name="B")
    templates_before = row_counts(db)["templates"]
    with db.write() as conn:
        event = record_merge_event(conn=conn, spec=MergeEventSpec(
            map_id=b.meta.map.id, map_name="B", mode="offline", confirmations=3, lattice_offset=[1.0, -2.0, 3.0],
            transform=(0.5, 0.25, 0.0, 0.0, 0.0, 0.0, 1.0), yaw=0.0,
            matches={"templates": [{"target": 0, "source": 2}]},
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
    merged = load_map(db, name="B")
    assert [s.name for s in merged.meta.sessions] == ["a", "b"]
    assert row_counts(db)["templates"] == templates_before  # A's templates moved, not copied
    with db.read() as conn:
        blobs = conn.execute(MapArchive.__table__.select()).all()
        record = get_merge_event(conn=conn, event_id=event)
        pixels = sum(x.snapshot["lv_templates"].nbytes for x in (a, b))
        assert sum(len(row.state) for row in blobs) < pixels / 4  # references, not pixel copies
    assert record.sessions == {a.meta.sessions[0].id: "source", b.meta.sessions[0].id: "target"}
    assert len(record.archive_ids) == 2 and record.status == "applied" and record.lattice_offset == [1.0, -2.0, 3.0]

    with db.write() as conn:  # unmerge
        restore_map_states(conn=conn, archive_ids=record.archive_ids)
        set_merge_status(conn=conn, event_id=event, status="undone")
    a2, b2 = load_map(db, name="A"), load_map(db, name="B")
    assert_same_arrays(a.snapshot, a2.snapshot)
    assert_same_arrays(b.snapshot, b2.snapshot)
    assert [s.name for s in a2.meta.sessions] == ["a"] and [s.name for s in b2.meta.sessions] == ["b"]
    assert np.array_equal(a2.meta.experience_index, a.meta.experience_index)
    with db.read() as conn:
        assert get_merge_event(conn=conn, event_id=event).status == "undone"
        assert [e.id for e in list_merge_events(conn=conn, map_id=get_map(conn=conn, name="B").id)] == [event]
    assert row_counts(db)["templates"] == templates_before


def test_an_in_memory_state_is_archived_with_its_pixels_inline(db: Database) -> None:
    params = small_params()
    snap = drive_engine(params, laps=0.8).snapshot()
    save_map(db, name="A", params=params, snapshot=snap, sessions=[_session("a")])
    a = load_map(db, name="A")
    sid = a.meta.sessions[0].id
    partial = dict(a.snapshot)
    partial["em_pose"] = partial["em_pose"] * 2.0
    extra = np.full((1, *snap["lv_templates"].shape[1:]), 0.25, dtype=np.float32)
    partial["lv_templates"] = np.concatenate([partial["lv_templates"], extra])  # one template never stored
    partial["lv_means"] = np.concatenate([partial["lv_means"], [0.25]])
    partial["lv_origin"] = np.concatenate([partial["lv_origin"], [sid]])
    with db.write() as conn:
        archive_id = archive_state(
            conn=conn, map_name="P", params=params, snapshot=partial, session_ids=[sid],
            template_session=partial["lv_origin"], template_index=np.arange(partial["lv_means"].shape[0]),
            experience_session=a.meta.experience_session, experience_index=a.meta.experience_index,
        )  # fmt: skip
    with db.read() as conn:
        back = load_archive(conn=conn, archive_id=archive_id)
        with pytest.raises(NotFoundError):
            load_archive(conn=conn, archive_id=archive_id + 100)
    assert_same_arrays(partial, back.snapshot)
    assert back.map_name == "P" and back.session_ids == (sid,)


def test_an_archive_keeps_its_sessions_progress_exactly_and_a_merged_archive_stays_apart(db: Database) -> None:
    params = small_params()
    save_map(db, name="A", params=params, snapshot=drive_engine(params, laps=0.5, seed=2).snapshot(),
             sessions=[_session("a"), _session("b")])  # fmt: skip
    a = load_map(db, name="A")
    first, second = (s.id for s in a.meta.sessions)
    rows = np.arange(24, dtype=np.float64).reshape(6, 4) - 0.0
    rows[0, 1] = -0.0  # the sign of zero and the blob's bytes come back as they were
    with db.write() as conn:
        set_activations(conn=conn, session_id=first, rows=rows[:, ::-1])
        cut_session(conn=conn, session_id=first, frames=6, status="complete", last_stamp=12.5,
                    reckoning_pose=(1.0, -2.0, 0.0, 0.5))  # fmt: skip
        kept = [get_session_progress(conn=conn, session_id=s) for s in (first, second)]
        event = record_merge_event(conn=conn, spec=MergeEventSpec(
            map_id=a.meta.map.id, map_name="A", mode="offline", confirmations=1, lattice_offset=[0.0, 0.0, 0.0],
            transform=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0), yaw=0.0, matches={}, target_sessions=[first],
            source_sessions=[second],
        ))  # fmt: skip
        target = archive_map_state(conn=conn, map_id=a.meta.map.id, event_id=event, role="target")
        merged = archive_map_state(conn=conn, map_id=a.meta.map.id, event_id=event, role="merged", progress=kept)
        cut_session(conn=conn, session_id=first, frames=2, status="partial", last_stamp=3.0, reckoning_pose=None)
    with db.read() as conn:
        record = get_merge_event(conn=conn, event_id=event)
        assert (record.archive_ids, record.merged_archive) == ([target], merged)  # a redo's, not an undo's
        assert get_session_progress(conn=conn, session_id=first).frames_processed == 2
        back = load_archive(conn=conn, archive_id=merged)
        assert load_archive(conn=conn, archive_id=target).progress == ()
    assert back.progress == tuple(kept) and (kept[0].reckoning, kept[1].reckoning) == (b"", None)  # empty, none
    with db.write() as conn:
        restore_progress(conn=conn, archived=back)
        assert [get_session_progress(conn=conn, session_id=s) for s in (first, second)] == kept
        delete_archive(conn=conn, archive_id=merged)
    with db.read() as conn:
        assert get_merge_event(conn=conn, event_id=event).merged_archive is None
        assert np.array_equal(get_activations(conn=conn, session_id=first), rows[:, ::-1])

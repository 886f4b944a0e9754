"""Storing is one transaction: a failure injected halfway through the inserts leaves no rows behind."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mapserver.processing import pipeline
from mapserver.store import Database, NewSession, UnknownMapError, load_map, save_map
from mapserver.store import state_rows_write as rows_module
from tests.mapserver.store.conftest import (
    assert_same_arrays,
    drive_engine,
    row_counts,
    small_params,
    write_loop_log,
)


class InjectedCrashError(RuntimeError):
    """The simulated crash."""


def _session(name: str) -> NewSession:
    params = small_params()
    return NewSession(
        name=name, log_name=f"{name}.bag", log_sha256=name.ljust(64, "0"), topics={}, params=params.to_dict()
    )


def _crash_after_experiences(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Make the link inserts fail after templates, pose-cell links and experiences were inserted."""
    seen: list[int] = []
    real = rows_module._insert_experiences

    def insert_then_remember(conn, map_id, snapshot, *args):  # type: ignore[no-untyped-def]
        real(conn, map_id, snapshot, *args)
        seen.append(int(np.asarray(snapshot["em_pose"]).shape[0]))

    def crash(*_args, **_kwargs):  # type: ignore[no-untyped-def]
        raise InjectedCrashError("simulated crash halfway through the inserts")

    monkeypatch.setattr(rows_module, "_insert_experiences", insert_then_remember)
    monkeypatch.setattr(rows_module, "_insert_links", crash)
    return seen


def test_a_crash_while_creating_a_map_leaves_no_rows(db: Database, monkeypatch: pytest.MonkeyPatch) -> None:
    engine = drive_engine(small_params(), laps=1.2)
    empty = row_counts(db)
    assert set(empty.values()) == {0}
    seen = _crash_after_experiences(monkeypatch)
    with pytest.raises(InjectedCrashError):
        save_map(db, name="lab", params=engine.params, snapshot=engine.snapshot(), sessions=[_session("s")])
    assert seen == [engine.experience_count] and seen[0] > 0  # the crash came after real inserts
    assert row_counts(db) == empty
    with pytest.raises(UnknownMapError):
        load_map(db, name="lab")


def test_a_crash_while_updating_a_map_keeps_the_old_state(db: Database, monkeypatch: pytest.MonkeyPatch) -> None:
    params = small_params()
    short = drive_engine(params, laps=1.0)
    save_map(db, name="lab", params=params, snapshot=short.snapshot(), sessions=[_session("s")])
    before = load_map(db, name="lab")
    counts = row_counts(db)
    longer = drive_engine(params, laps=2.2, origin=before.meta.sessions[0].id)
    _crash_after_experiences(monkeypatch)
    with pytest.raises(InjectedCrashError):
        save_map(
            db, name="lab", params=params, snapshot=longer.snapshot(), sessions=[before.meta.sessions[0].id],
            expected_version=before.meta.map.version,
        )  # fmt: skip
    after = load_map(db, name="lab")
    assert row_counts(db) == counts
    assert after.meta.map.version == before.meta.map.version
    assert_same_arrays(before.snapshot, after.snapshot)


@pytest.mark.slow
def test_a_crash_while_storing_a_processed_log_leaves_no_rows(
    db_url: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    log = write_loop_log(tmp_path / "loop.bag", laps=0.8)
    from mapserver.store import evidence

    def crash(**_kwargs):  # type: ignore[no-untyped-def]
        raise InjectedCrashError("simulated crash while storing evidence, after the map state")

    monkeypatch.setattr(evidence, "save_evidence", crash)
    with pytest.raises(InjectedCrashError):
        pipeline.process_into_store(log, small_params(), db_url=db_url)
    from mapserver.store import open_database

    with open_database(db_url) as db:
        assert set(row_counts(db).values()) == {0}

"""Two real processes writing the same map never interleave: one wins, the other gets StaleMapError.

The first writer holds its transaction open (everything written, not committed) while a second process
reads the map and then tries to write it. The reader sees the old state exactly (never half of the
new one); the second writer waits for the first and is refused; the final state is the winner's, whole.
"""

from __future__ import annotations

import multiprocessing as mp
import threading
import time
import traceback
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapserver.store import Database, NewSession, create_db_engine, load_map, open_database, save_map, write_map_state
from tests.mapserver.store.conftest import digest, drive_engine, small_params

HOLD_S = 2.0


def _changed(snapshot: dict[str, np.ndarray], shift: float) -> dict[str, np.ndarray]:
    out = dict(snapshot)
    out["em_pose"] = snapshot["em_pose"] + shift
    out["pc_activity"] = np.roll(snapshot["pc_activity"], 1, axis=0)
    return out


def _slow_writer(url: str, ready: Any, written: Any, out: Any) -> None:
    """Load the map, wait for the others, write a changed state and hold the transaction open."""
    try:
        with open_database(url) as db:
            content = load_map(db, name="shared")
            ready.wait(30)
            target = _changed(content.snapshot, 1.0)
            with db.write() as conn:
                write_map_state(
                    conn=conn, map_id=content.meta.map.id, expected_version=content.meta.map.version,
                    params=content.params, snapshot=target, session_ids=[s.id for s in content.meta.sessions],
                )  # fmt: skip
                written.set()
                time.sleep(HOLD_S)
            out.put(("writer", "committed", digest(target)))
    except Exception:
        out.put(("writer", "error", traceback.format_exc()))


def _reader_then_writer(url: str, ready: Any, written: Any, out: Any) -> None:
    """Load the map (version v), wait until the first writer has written, read again, then write."""
    try:
        with open_database(url) as db:
            content = load_map(db, name="shared")
            ready.wait(30)
            written.wait(30)
            during = load_map(db, name="shared")
            out.put(("reader", "during", digest(during.snapshot), during.meta.map.version))
            target = _changed(content.snapshot, 2.0)
            started = time.perf_counter()
            try:
                save_map(
                    db, name="shared", params=content.params, snapshot=target,
                    sessions=[s.id for s in content.meta.sessions], expected_version=content.meta.map.version,
                )  # fmt: skip
                out.put(("second", "committed", digest(target)))
            except Exception as err:
                out.put(("second", type(err).__name__, str(err), time.perf_counter() - started))
    except Exception:
        out.put(("reader", "error", traceback.format_exc()))


def test_two_processes_never_interleave_a_map(db: Database, db_url: str) -> None:
    params = small_params()
    engine = drive_engine(params, laps=1.5)
    session = NewSession(name="s", log_name="s.bag", log_sha256="c" * 64, topics={}, params=params.to_dict())
    save_map(db, name="shared", params=params, snapshot=engine.snapshot(), sessions=[session])
    original = load_map(db, name="shared")
    context = mp.get_context("spawn")
    ready = context.Barrier(2)
    written = context.Event()
    out = context.Queue()
    procs = [
        context.Process(target=_slow_writer, args=(db_url, ready, written, out)),
        context.Process(target=_reader_then_writer, args=(db_url, ready, written, out)),
    ]
    for p in procs:
        p.start()
    messages = [out.get(timeout=120) for _ in range(3)]
    for p in procs:
        p.join(60)
    by_role = {m[0]: m for m in messages}
    assert "error" not in {m[1] for m in messages}, messages
    # the reader saw the old state, whole, while the first writer held its transaction
    assert by_role["reader"][1:] == ("during", digest(original.snapshot), original.meta.map.version)
    # the second writer waited for the first one and was refused
    assert by_role["second"][1] == "StaleMapError", by_role["second"]
    assert by_role["second"][3] > 0.5 * HOLD_S
    assert by_role["writer"][1] == "committed"
    final = load_map(db, name="shared")
    assert digest(final.snapshot) == by_role["writer"][2]
    assert final.meta.map.version == original.meta.map.version + 1


def _open_empty(url: str, out: Any) -> None:
    try:
        open_database(url).dispose()
        out.put("ok")
    except Exception:
        out.put(traceback.format_exc())


@pytest.mark.parametrize("db_url", ["sqlite", "postgresql"], indirect=True)
def test_two_processes_opening_an_empty_database_create_the_schema_once(db_url: str) -> None:
    context = mp.get_context("spawn")
    out = context.Queue()
    procs = [context.Process(target=_open_empty, args=(db_url, out)) for _ in range(2)]
    for p in procs:
        p.start()
    results = [out.get(timeout=120) for _ in procs]
    for p in procs:
        p.join(60)
    assert results == ["ok", "ok"]


def test_connections_opening_a_fresh_sqlite_file_together_wait_for_its_switch_to_wal(tmp_path: Path) -> None:
    # SQLite refuses the second of two connections switching a new file to WAL at once with an
    # immediate "database is locked" (no busy wait): without a retry ~6 % of these pairs failed.
    def connect(url: str, barrier: threading.Barrier) -> str:
        engine = create_db_engine(url)
        try:
            barrier.wait(10)
            with engine.connect() as conn:
                return str(conn.exec_driver_sql("PRAGMA journal_mode").scalar())
        finally:
            engine.dispose()

    with ThreadPoolExecutor(2) as pool:
        for i in range(200):
            url = f"sqlite:///{tmp_path / f'{i}.db'}"
            barrier = threading.Barrier(2)
            modes = [f.result() for f in [pool.submit(connect, url, barrier) for _ in range(2)]]
            assert modes == ["wal", "wal"]

"""Merges one can manage: merge → unmerge → merge again, and merge → unmerge → redo, bit for bit; moving a session out.

Small Virtual Tour (ellipse at half scale, the README's missions): session 2 merges online into session 1 at its
22nd frame (34 experiences merged, 25 of session 1, 11 of session 2 before the merge). Every state is compared by
:func:`digest`: SHA-256 of the map's JSON export, every snapshot array (name, dtype, shape, bytes), the rows'
stable identities and the sessions' progress rows (status, frames, stamps, dead reckoning, timeline).
"""

from __future__ import annotations

import hashlib
import sqlite3
from contextlib import closing
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from core import preset
from mapserver.api import create_app
from mapserver.atlas import undo
from mapserver.errors import ConflictError
from mapserver.processing import pipeline
from mapserver.store import load_map, open_database
from mapserver.store.archive import delete_archive
from mapserver.store.merge_events import get_merge_event
from mapserver.store.sessions import get_activations, get_session_progress
from mapserver.store.streams import open_export
from tests.mapserver.api.conftest import api_settings, bearer, make_token
from tests.mapserver.merge.scenario_metrics import cli_code, cli_json
from tests.simulations import simulate_once

pytestmark = pytest.mark.slow

PARAMS = preset("circle")


def digest(url: str, name: str, *, export: bool = True) -> str:
    """Return the SHA-256 of a stored map: export JSON (``export``), snapshot, identities and sessions' progress."""
    h = hashlib.sha256()
    with open_database(url) as db:
        if export:
            for chunk in open_export(db, name=name, fmt="json"):
                h.update(chunk)
        content = load_map(db, name=name)
        for key, value in content.snapshot.items():
            h.update(f"{key}|{value.dtype.str}|{value.shape}".encode())
            h.update(np.ascontiguousarray(value).tobytes())
        meta = content.meta
        for ids in (meta.template_session, meta.template_index, meta.experience_session, meta.experience_index):
            h.update(ids.tobytes())
        with db.read() as conn:
            for s in meta.sessions:
                p = get_session_progress(conn=conn, session_id=s.id)
                h.update(repr((s.name, p.status, p.frames_processed, p.last_stamp, p.reckoning_pose,
                               p.finished_at)).encode())  # fmt: skip
                h.update(p.reckoning or b"-")
                h.update(p.activations or b"-")
    return h.hexdigest()


def maps_of(url: str) -> dict[str, tuple[int, int]]:
    """Return map name → (sessions, experiences)."""
    return {m["name"]: (m["sessions"], m["experiences"]) for m in cli_json("maps", "--db", url)["maps"]}


def copy_db(src: Path, dst: Path) -> str:
    """Copy a SQLite atlas (the backup API: WAL content included); return its URL."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    with closing(sqlite3.connect(src)) as a, closing(sqlite3.connect(dst)) as b:
        a.backup(b)
    return f"sqlite:///{dst}"


@pytest.fixture(scope="module")
def atlases(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Session 1 alone; sessions 1 and 2 merged online; the two apart (``--no-merge``); digests of the maps."""
    root = tmp_path_factory.mktemp("cycle")
    tour = root / "tour"
    simulate_once("ellipse", tour, scale=0.5, params={"single_laps": 1, "session2_laps": 1})
    alone = root / "alone.db"
    pipeline.process_into_store(tour / "session1.bag", PARAMS, db_url=f"sqlite:///{alone}")
    online, apart = copy_db(alone, root / "online.db"), copy_db(alone, root / "apart.db")
    merged = pipeline.process_into_store(tour / "session2.bag", PARAMS, db_url=online)
    pipeline.process_into_store(tour / "session2.bag", PARAMS, db_url=apart, merge=False)
    return {"tour": tour, "online": root / "online.db", "apart": root / "apart.db", "merge": merged.merges[0],
            "session1": digest(f"sqlite:///{alone}", "session1"), "apart1": digest(apart, "session1"),
            "apart2": digest(apart, "session2"), "apart1_rows": digest(apart, "session1", export=False),
            "apart2_rows": digest(apart, "session2", export=False)}  # fmt: skip


def _copy(atlases: dict[str, Any], which: str, tmp_path: Path) -> str:
    return copy_db(atlases[which], tmp_path / f"{which}.db")


def test_redo_of_an_online_merge_gives_back_every_experience_bit_for_bit(
    atlases: dict[str, Any], tmp_path: Path
) -> None:
    url = _copy(atlases, "online", tmp_path)
    event = atlases["merge"]["event"]
    merged = digest(url, "session1")
    assert maps_of(url) == {"session1": (2, 34)}
    undone = cli_json("unmerge", "--db", url, "--event", str(event))
    assert undone == {"unmerged": True, "event": event, "maps": ["session1", "session2"], "session": "session2",
                      "frames": atlases["merge"]["frame"] + 1, "session_status": "complete"}  # fmt: skip
    assert maps_of(url) == {"session1": (1, 25), "session2": (1, 11)}  # the merge taken apart
    assert digest(url, "session1") == atlases["session1"]  # session 1 as before the merge, bit for bit
    assert cli_json("merge", "--db", url, "--redo", str(event))["map"] == "session1"
    assert maps_of(url) == {"session1": (2, 34)}  # not 29: the frames after the merge are back
    assert digest(url, "session1") == merged
    again = pipeline.process_into_store(atlases["tour"] / "session2.bag", PARAMS, db_url=url)
    assert again.merges == [] and digest(url, "session1") == merged  # the log is answered as stored, no duplicate


def test_unmerge_leaves_both_maps_whole_and_mergeable_again(atlases: dict[str, Any], tmp_path: Path) -> None:
    url = _copy(atlases, "online", tmp_path)
    event = atlases["merge"]["event"]
    cli_json("unmerge", "--db", url, "--event", str(event))
    with open_database(url) as db:
        (session,) = load_map(db, name="session2").meta.sessions
    assert (session.status, session.frames_processed) == ("complete", atlases["merge"]["frame"] + 1)
    cut = digest(url, "session2")
    # merge → unmerge → merge → unmerge → merge: each merge the same map, each unmerge the same two maps
    results = []
    for _ in range(2):
        done = cli_json("merge", "--db", url, "--map", "session2", "--into", "session1")
        results.append(digest(url, "session1"))
        assert maps_of(url) == {"session1": (2, 29)}
        cli_json("unmerge", "--db", url, "--event", str(done["event"]))
        assert (digest(url, "session1"), digest(url, "session2")) == (atlases["session1"], cut)
    assert results[0] == results[1]
    # the first event's redo would overwrite what happened since its undo: refused, nothing written
    code, err = cli_code("merge", "--db", url, "--redo", str(event))
    assert code == 1 and "changed after merge event 1 was undone" in err
    assert (digest(url, "session1"), digest(url, "session2")) == (atlases["session1"], cut)


def test_an_unmerge_that_rewinds_leaves_the_session_to_continue_and_unmergeable(
    atlases: dict[str, Any], tmp_path: Path
) -> None:
    url = _copy(atlases, "online", tmp_path)
    event, frame = atlases["merge"]["event"], atlases["merge"]["frame"]
    assert cli_json("unmerge", "--db", url, "--event", str(event), "--rewind")["session_status"] == "partial"
    code, err = cli_code("merge", "--db", url, "--map", "session2", "--into", "session1")
    assert code == 1 and "still being processed (partial)" in err
    rest = pipeline.process_into_store(atlases["tour"] / "session2.bag", PARAMS, db_url=url, merge=False)
    assert rest.frames_run == rest.frames - frame - 1 and maps_of(url)["session2"][0] == 1  # continued to its end
    with open_database(url) as db, db.read() as conn:  # one timeline row per frame (the rows after the merge were cut)
        assert get_activations(conn=conn, session_id=rest.session_id).shape == (rest.frames, 4)
    code, err = cli_code("merge", "--db", url, "--redo", str(event))
    assert code == 1 and "map 'session2' changed after merge event 1 was undone" in err


def test_offline_merge_unmerge_merge_redo(atlases: dict[str, Any], tmp_path: Path) -> None:
    url = _copy(atlases, "apart", tmp_path)
    first = cli_json("merge", "--db", url, "--map", "session2", "--into", "session1")["event"]
    merged = digest(url, "session1")
    cli_json("unmerge", "--db", url, "--event", str(first))
    assert (digest(url, "session1"), digest(url, "session2")) == (atlases["apart1"], atlases["apart2"])
    second = cli_json("merge", "--db", url, "--map", "session2", "--into", "session1")["event"]
    assert second == first + 1 and digest(url, "session1") == merged  # the same merge, the same map
    cli_json("unmerge", "--db", url, "--event", str(second))
    assert (digest(url, "session1"), digest(url, "session2")) == (atlases["apart1"], atlases["apart2"])
    assert cli_json("merge", "--db", url, "--redo", str(second))["event"] == second
    assert digest(url, "session1") == merged and set(maps_of(url)) == {"session1"}
    code, err = cli_code("merge", "--db", url, "--redo", str(second))
    assert code == 1 and "only an undone event can be redone" in err
    assert digest(url, "session1") == merged
    # an event undone before unmerges archived the merged map is merged again from its archives: the same map
    cli_json("unmerge", "--db", url, "--event", str(second))
    with open_database(url) as db, db.write() as conn:
        delete_archive(conn=conn, archive_id=get_merge_event(conn=conn, event_id=second).merged_archive)
    cli_json("merge", "--db", url, "--redo", str(second))
    assert digest(url, "session1") == merged


def test_moving_a_session_out_leaves_the_rest_whole(atlases: dict[str, Any], tmp_path: Path) -> None:
    url, apart = _copy(atlases, "apart", tmp_path), f"sqlite:///{atlases['apart']}"
    event = cli_json("merge", "--db", url, "--map", "session2", "--into", "session1")["event"]
    merged = digest(url, "session1")
    moved = cli_json("session", "move", "session1", "--db", url)  # the map's own first session
    assert moved == {"moved": True, "session": "session1", "map": "session1-2", "rest": "session1", "event": event,
                     "frames": None}  # fmt: skip
    assert maps_of(url) == {"session1": maps_of(apart)["session2"], "session1-2": (1, 25)}
    # each as it was before the merge, under its new name (the export, which names the map, aside)
    assert digest(url, "session1-2", export=False) == atlases["apart1_rows"]
    assert digest(url, "session1", export=False) == atlases["apart2_rows"]
    cli_json("merge", "--db", url, "--redo", str(event))
    assert digest(url, "session1") == merged and set(maps_of(url)) == {"session1"}
    assert cli_json("session", "move", "session2", "--db", url, "--to", "two")["map"] == "two"
    assert (digest(url, "session1"), digest(url, "two", export=False)) == (atlases["apart1"], atlases["apart2_rows"])
    # refused: alone already, unknown, a taken or invalid name; nothing changes
    before = {name: digest(url, name) for name in ("session1", "two")}
    for args, code, text in [
        (["session2"], 1, "is the only session of map 'two'"),
        (["nobody"], 2, "no session named 'nobody'"),
        (["session2", "--to", "bad name"], 2, "invalid map name 'bad name'"),
    ]:
        got, err = cli_code("session", "move", *args, "--db", url)
        assert (got, err.strip().splitlines()[-1].startswith("ERROR: ")) == (code, True) and text in err
    assert {name: digest(url, name) for name in ("session1", "two")} == before


def test_an_entangled_session_is_refused_and_says_why(atlases: dict[str, Any], tmp_path: Path) -> None:
    url = _copy(atlases, "online", tmp_path)
    merged = digest(url, "session1")
    entangled = r"session 'session2' was merged into session 'session1'.s map online"
    with open_database(url) as db, pytest.raises(ConflictError, match=entangled):
        undo.move_session(db, session="session1")
    assert digest(url, "session1") == merged  # nothing written
    with open_database(url) as db:  # the online session itself moves out: the frames it had when it merged
        out = undo.move_session(db, session="session2", map_name="mine")
    assert (out.map, out.rest, out.frames) == ("mine", "session1", atlases["merge"]["frame"] + 1)
    assert digest(url, "session1") == atlases["session1"]
    # three sessions: 1 and 2 merged first, then 'single' into them; 1 and 2 cannot part, 'single' can
    url = _copy(atlases, "apart", tmp_path / "three")
    cli_json("merge", "--db", url, "--map", "session2", "--into", "session1")
    pipeline.process_into_store(atlases["tour"] / "single.bag", PARAMS, db_url=url, merge=False)
    two = digest(url, "session1")
    cli_json("merge", "--db", url, "--map", "single", "--into", "session1")
    code, err = cli_code("session", "move", "session2", "--db", url)
    assert code == 1 and "together with session(s) 'session1', merged with it earlier" in err
    assert cli_json("session", "move", "single", "--db", url)["map"] == "single"
    assert digest(url, "session1") == two


def test_rest_move_and_undo_with_rewind(atlases: dict[str, Any], tmp_path: Path) -> None:
    url = _copy(atlases, "apart", tmp_path)
    event = cli_json("merge", "--db", url, "--map", "session2", "--into", "session1")["event"]
    settings = api_settings(tmp_path, db_url=url)
    write, read = bearer(make_token(url, "write")), bearer(make_token(url, "read"))
    with TestClient(create_app(settings)) as client:
        assert client.post("/v1/sessions/session2/move", headers=read).status_code == 403
        assert client.post("/v1/sessions/nobody/move", headers=write).status_code == 404
        bad = client.post("/v1/sessions/session2/move", params={"to": "bad name"}, headers=write)
        assert bad.status_code == 400 and "invalid map name" in bad.json()["detail"]
        taken = client.post("/v1/sessions/session2/move", params={"to": "session1"}, headers=write)
        assert taken.status_code == 409 and taken.json()["detail"] == "a map named 'session1' already exists"
        moved = client.post("/v1/sessions/session2/move", params={"to": "two"}, headers=write)
        expected = {"moved": True, "session": "session2", "map": "two", "rest": "session1", "event": event,
                    "frames": None}  # fmt: skip
        assert moved.status_code == 200 and moved.json() == expected
        again = client.post("/v1/sessions/session2/move", headers=write)
        assert again.status_code == 409 and "only session of map 'two'" in again.json()["detail"]
    assert digest(url, "session1") == atlases["apart1"]
    online = _copy(atlases, "online", tmp_path)
    settings = api_settings(tmp_path / "o", db_url=online)
    with TestClient(create_app(settings)) as client:
        undone = client.post(f"/v1/merges/{atlases['merge']['event']}/undo", params={"rewind": "true"},
                             headers=bearer(make_token(online, "write")))  # fmt: skip
    body = undone.json()
    assert undone.status_code == 200 and (body["status"], body["session_status"], body["frames"]) == (
        "undone", "partial", atlases["merge"]["frame"] + 1)  # fmt: skip

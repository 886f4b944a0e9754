"""Merges through the store (``mapserver.atlas`` with ``pipeline``): resume, undo, redo, offline merge, concurrency.

Small Virtual Tour (ellipse at half scale; session 2 drives 1.25 laps and merges at its 12th frame).
"""

from __future__ import annotations

import logging
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy.engine import make_url as sa_url

from core import preset
from mapserver import atlas
from mapserver.api import Settings, create_app
from mapserver.errors import ConflictError, MergeError, NoConfirmedMatchError
from mapserver.ingest.reader import MissionLog
from mapserver.ingest.simulator import simulate
from mapserver.processing import pipeline
from mapserver.store import load_map, open_database, save_map
from mapserver.store.merge_events import get_merge_event, list_merge_events
from mapserver.store.sessions import get_reckoning
from tests.mapserver.api.logs import write_strip_log
from tests.mapserver.merge.scenario_metrics import cli_code, cli_json
from tests.mapserver.store.conftest import assert_same_arrays, db_url, make_url, row_counts  # noqa: F401

pytestmark = pytest.mark.slow

PARAMS = preset("circle")


@pytest.fixture(scope="module")
def tour(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("tour")
    simulate("ellipse", directory, seed=0, scale=0.5, params={"session2_laps": 1.25, "single_laps": 0.6})
    return directory


def _snapshot(url: str, name: str) -> dict[str, np.ndarray]:
    with open_database(url) as db:
        return load_map(db, name=name).snapshot


def _engine_keys(snapshot: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: v for k, v in snapshot.items() if not k.startswith(("mg_", "st_"))}


@pytest.mark.parametrize("stop", [5, 30], ids=["stop-before-the-merge", "stop-after-the-merge"])
def test_resuming_a_merging_session_equals_one_run(tour: Path, db_url: str, make_url: Any, stop: int) -> None:  # noqa: F811
    pipeline.process_into_store(tour / "session1.bag", PARAMS, db_url=db_url)
    whole = pipeline.process_into_store(tour / "session2.bag", PARAMS, db_url=db_url)
    (merge_frame,) = [m["frame"] for m in whole.merges]
    assert 5 < merge_frame < 30 and whole.merges[0]["status"] == "applied"
    split = make_url()
    pipeline.process_into_store(tour / "session1.bag", PARAMS, db_url=split)
    first = pipeline.process_into_store(tour / "session2.bag", PARAMS, db_url=split, stop_after=stop)
    second = pipeline.process_into_store(tour / "session2.bag", PARAMS, db_url=split)
    assert [m["frame"] for m in first.merges + second.merges] == [merge_frame]
    assert first.map_name == ("session2" if stop <= merge_frame else "session1") and second.map_name == "session1"
    assert first.frames_run >= stop and second.frames_run == whole.frames - first.frames_run
    assert second.summary()["frames_per_s"] is not None
    # a stop inside the probation moves to its end: the stored merge is verified as in one run, never "incomplete"
    verified = [m["evidence"]["verification"]["status"] for m in first.merges + second.merges]
    assert verified == [whole.merges[0]["evidence"]["verification"]["status"]] == ["passed"]
    assert_same_arrays(_snapshot(db_url, "session1"), _snapshot(split, "session1"))
    with open_database(db_url) as a, open_database(split) as b:
        assert row_counts(a)["experiences"] == row_counts(b)["experiences"]
        meta_a, meta_b = load_map(a, name="session1").meta, load_map(b, name="session1").meta
        assert meta_a.experience_index.tobytes() == meta_b.experience_index.tobytes()
        assert meta_a.template_index.tobytes() == meta_b.template_index.tobytes()


def _api_merge_events(url: str, tmp_path: Path, name: str) -> list[dict[str, Any]]:
    settings = Settings(db_url=url, upload_dir=tmp_path / "uploads", allow_anonymous_reads=True)
    with TestClient(create_app(settings)) as client:
        response = client.get(f"/v1/maps/{name}")
    assert response.status_code == 200, response.text
    return response.json()["merge_events"]


def test_unmerge_restores_the_maps_exactly_and_redo_reproduces_the_merge(
    tour: Path,
    tmp_path: Path,
    db_url: str,  # noqa: F811
    make_url: Any,  # noqa: F811
) -> None:
    pipeline.process_into_store(tour / "session1.bag", PARAMS, db_url=db_url)
    before = _snapshot(db_url, "session1")
    merged = pipeline.process_into_store(tour / "session2.bag", PARAMS, db_url=db_url)
    summary = merged.summary()
    (entry,) = summary["merges"]
    assert set(entry) >= {"event", "into", "map", "frame", "stamp", "confirmations", "matched_templates",
                          "transform", "lattice_offset"}  # fmt: skip
    assert entry["into"] == entry["map"] == summary["map"] == "session1" and entry["confirmations"] >= 3
    final = _snapshot(db_url, "session1")
    with open_database(db_url) as db, db.read() as conn:
        event = get_merge_event(conn=conn, event_id=entry["event"])
    assert (event.mode, event.status, event.confirmations) == ("online", "applied", entry["confirmations"])
    assert sorted(event.sessions.values()) == ["source", "target"] and len(event.archive_ids) == 2
    assert len(event.matches["templates"]) == entry["matched_templates"] >= 2
    assert event.details["frame"] == entry["frame"] and len(event.lattice_offset) == 3
    assert len(event.details["session_pose"]) == 4  # the robot in session 2's map frame when it merged
    shown = _api_merge_events(db_url, tmp_path, "session1")  # the provenance GET /v1/maps/{name} shows
    assert [(e["id"], e["mode"], e["status"], e["confirmations"]) for e in shown] == [
        (entry["event"], "online", "applied", entry["confirmations"])]  # fmt: skip
    assert shown[0]["sessions"] == {"session1": "target", "session2": "source"}
    assert shown[0]["lattice_offset"] == pytest.approx(entry["lattice_offset"])
    assert shown[0]["transform"] == pytest.approx(list(event.transform)) and shown[0]["matches"] == event.matches

    rewound = cli_json("unmerge", "--db", db_url, "--event", str(entry["event"]), "--rewind")
    assert (rewound["frames"], rewound["session_status"]) == (entry["frame"] + 1, "partial")
    assert_same_arrays(before, _snapshot(db_url, "session1"))  # the stored map, bit for bit
    alone = make_url()  # the partial map = session 2 processed alone up to the merge frame
    pipeline.process_into_store(tour / "session2.bag", PARAMS, db_url=alone, merge=False, stop_after=entry["frame"] + 1)
    expected, restored = _snapshot(alone, "session2"), _snapshot(db_url, "session2")
    assert_same_arrays(_engine_keys(expected), _engine_keys(restored), skip=("lv_origin", "em_origin"))
    with open_database(db_url) as db, db.read() as conn:
        session = load_map(db, name="session2").meta.sessions[0]
        rows, _pose = get_reckoning(conn=conn, session_id=session.id)
        at = entry["frame"] + 1
        assert (session.status, session.frames_processed, rows.shape[0]) == ("partial", at, at)
    code, err = cli_code("unmerge", "--db", db_url, "--event", str(entry["event"]))
    assert code == 1 and err.strip().splitlines()[-1] == f"ERROR: merge event {entry['event']} is undone already"

    assert cli_json("merge", "--db", db_url, "--redo", str(entry["event"])) == {
        "merged": True, "event": entry["event"], "map": "session1", "settled": True}  # fmt: skip
    assert_same_arrays(final, _snapshot(db_url, "session1"))  # the merged map as the unmerge found it
    again = pipeline.process_into_store(tour / "session2.bag", PARAMS, db_url=db_url)  # the stored session
    assert again.merges == [] and again.frames == merged.frames
    assert_same_arrays(final, _snapshot(db_url, "session1"))
    code, err = cli_code("merge", "--db", db_url, "--redo", str(entry["event"]))
    assert code == 1 and "only an undone event can be redone" in err


def test_unmerge_refuses_while_a_later_merge_involves_the_same_sessions(tour: Path, tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'atlas.db'}"
    for log in ("session1", "session2", "single"):
        pipeline.process_into_store(tour / f"{log}.bag", PARAMS, db_url=url)
    with open_database(url) as db, db.read() as conn:
        events = list_merge_events(conn=conn)
    assert [e.status for e in events] == ["applied", "applied"]  # single starts where session 1 did: known start
    first, second = events[0].id, events[1].id
    known = events[1].details  # single starts where session 1 did: it activates that experience and maps on
    # it merges once the evidence distance is driven; everything it made by then is identified
    assert known["frame"] <= 20 and known["record"]["experiences"] == known["record"]["experience_offset"]
    code, err = cli_code("unmerge", "--db", url, "--event", str(first))
    assert code == 1
    assert err.strip().splitlines()[-1] == (
        f"ERROR: merge event {second} (later) involves the same sessions; undo it first "
        "(merge events are undone newest first)"
    )
    cli_json("unmerge", "--db", url, "--event", str(second))
    cli_json("unmerge", "--db", url, "--event", str(first))
    maps = cli_json("maps", "--db", url)["maps"]
    assert sorted((m["name"], m["sessions"]) for m in maps) == [("session1", 1), ("session2", 1), ("single", 1)]


def test_offline_merge_refuses_without_a_match_and_undoes_and_redoes_exactly(
    tour: Path,
    db_url: str,  # noqa: F811
) -> None:
    for log in ("session1", "session2"):
        pipeline.process_into_store(tour / f"{log}.bag", PARAMS, db_url=db_url, merge=False)
    a, b = _snapshot(db_url, "session2"), _snapshot(db_url, "session1")
    with open_database(db_url) as db:
        counts = row_counts(db)
    code, err = cli_code("merge", "--db", db_url, "--map", "session2", "--into", "session1", "--confirm", "500")
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ERROR: no confirmed match of map 'session2' in map 'session1'")
    with open_database(db_url) as db:
        assert row_counts(db) == counts  # nothing written
    assert cli_code("merge", "--db", db_url, "--map", "session1", "--into", "session1")[0] == 2
    assert cli_code("merge", "--db", db_url, "--map", "nowhere", "--into", "session1")[0] == 2

    done = cli_json("merge", "--db", db_url, "--map", "session2", "--into", "session1")
    assert done == {"merged": True, "event": 1, "map": "session1", "settled": True}
    maps = cli_json("maps", "--db", db_url)["maps"]
    assert [(m["name"], m["sessions"]) for m in maps] == [("session1", 2)]
    assert maps[0]["templates"] < a["lv_means"].size + b["lv_means"].size  # matched templates not duplicated
    merged = _snapshot(db_url, "session1")
    cli_json("unmerge", "--db", db_url, "--event", "1")
    assert_same_arrays(a, _snapshot(db_url, "session2"))
    assert_same_arrays(b, _snapshot(db_url, "session1"))
    cli_json("merge", "--db", db_url, "--redo", "1")
    assert_same_arrays(merged, _snapshot(db_url, "session1"))


def test_a_concurrent_write_to_the_stored_map_makes_the_session_redo_its_merge(
    tour: Path,
    db_url: str,  # noqa: F811
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    pipeline.process_into_store(tour / "session1.bag", PARAMS, db_url=db_url)
    original = atlas.merge_candidates
    calls: list[int] = []

    def racing(conn: Any, **kwargs: Any) -> Any:
        found = original(conn, **kwargs)
        calls.append(len(found[0]))
        if len(calls) == 1:  # another writer saves the stored map after this session read it
            with open_database(db_url) as other:
                content = load_map(other, name="session1")
                save_map(other, name="session1", params=content.params, snapshot=content.snapshot,
                         sessions=[s.id for s in content.meta.sessions],
                         expected_version=content.meta.map.version)  # fmt: skip
        return found

    monkeypatch.setattr(atlas, "merge_candidates", racing)
    with caplog.at_level(logging.WARNING):
        result = pipeline.process_into_store(tour / "session2.bag", PARAMS, db_url=db_url)
    assert calls == [1, 1] and "processing the log again" in caplog.text
    assert len(result.merges) == 1 and result.map_name == "session1"
    with open_database(db_url) as db, db.read() as conn:
        assert len(list_merge_events(conn=conn)) == 1
        assert row_counts(db)["maps"] == 1 and row_counts(db)["map_archives"] == 2


def test_two_sessions_processed_at_once_still_merge(tour: Path, db_url: str) -> None:  # noqa: F811
    # Both runs read the (empty) atlas before either writes: a barrier at their first frame makes sure.
    barrier = threading.Barrier(2, timeout=60)

    def run(name: str) -> Any:
        met: list[bool] = []

        def meet(_done: int, _total: int) -> None:
            if not met:  # the first progress report of the first run (a second run goes on alone)
                met.append(True)
                barrier.wait()

        return pipeline.process_into_store(tour / f"{name}.bag", PARAMS, db_url=db_url, progress=meet)

    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(run, ["session1", "session2"]))
    # the run that wrote second saw a new map it may merge into, processed its log again, and merged
    assert sorted(len(r.merges) for r in results) == [0, 1]
    with open_database(db_url) as db, db.read() as conn:
        events = list_merge_events(conn=conn)
        maps = load_map(db, name=results[0].map_name).meta
        assert results[0].map_name == results[1].map_name
        assert sorted(s.name for s in maps.sessions) == ["session1", "session2"]
        assert all(s.complete for s in maps.sessions) and row_counts(db)["maps"] == 1
    assert [(e.mode, e.status) for e in events] == [("online", "applied")]


def test_sessions_of_unrelated_worlds_processed_at_once_are_stored_without_a_rerun(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The pair of the test above: the second writer finds a new map, but none of its views meets that map's
    templates (two strip worlds of different textures), so its run stands (mapserver.merge.relevance)."""
    logs = [write_strip_log(tmp_path / f"w{seed}.bag", seed=seed) for seed in (11, 19)]
    url = f"sqlite:///{tmp_path / 'atlas.db'}"
    barrier = threading.Barrier(2, timeout=60)

    def run(log: Path) -> Any:
        met: list[bool] = []

        def meet(_done: int, _total: int) -> None:
            if not met:
                met.append(True)
                barrier.wait()

        return pipeline.process_into_store(log, preset("irat"), db_url=url, progress=meet)

    with caplog.at_level(logging.INFO), ThreadPoolExecutor(2) as pool:
        results = list(pool.map(run, logs))
    assert "processing the log again" not in caplog.text
    assert "none of its views meets them: stored without a rerun" in caplog.text
    assert [len(r.merges) for r in results] == [0, 0]
    with open_database(url) as db:
        assert row_counts(db)["maps"] == 2 and row_counts(db)["sessions"] == 2


def test_a_processed_log_is_hashed_once(tour: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    original = MissionLog.sha256
    hashed: list[str] = []

    def counting(self: MissionLog) -> str:
        if self._sha256 is None:
            hashed.append(str(self.path))
        return original.fget(self)  # type: ignore[attr-defined,no-any-return]

    monkeypatch.setattr(MissionLog, "sha256", property(counting))
    pipeline.process_into_store(tour / "session1.bag", PARAMS, db_url=f"sqlite:///{tmp_path / 'a.db'}")
    assert len(hashed) == 1


def test_no_confirmed_match_exits_2_while_other_refused_merges_exit_1() -> None:
    assert (NoConfirmedMatchError.exit_code, NoConfirmedMatchError.http_status) == (2, 409)
    assert issubclass(NoConfirmedMatchError, MergeError) and issubclass(MergeError, ConflictError)
    assert (MergeError.exit_code, ConflictError.exit_code) == (1, 1)


def test_the_last_stale_retry_holds_the_commit_gate(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """A session whose candidate maps keep changing (CI: six uploads over three maps, two worker threads) is
    processed a last time holding this process's commit gate, so other threads' commits wait and it is not
    starved; the earlier tries run without it."""
    from mapserver.processing import pipeline
    from mapserver.store import StaleMapError
    from mapserver.store.db import commit_gate

    log = tmp_path / "strip.bag"
    write_strip_log(log)
    held: list[bool] = []

    def attempt(db: Any, *_args: Any) -> Any:
        gate = commit_gate(db)
        held.append(gate._is_owned())  # type: ignore[attr-defined]
        if len(held) < pipeline.STALE_ATTEMPTS:
            raise StaleMapError("the maps this session may merge into changed while it was processed")
        return "stored"

    monkeypatch.setattr(pipeline, "_process_session", attempt)
    url = f"sqlite:///{tmp_path / 'gate.db'}"
    assert pipeline.process_into_store(log, preset("irat"), db_url=url) == "stored"
    assert held == [False] * (pipeline.STALE_ATTEMPTS - 1) + [True]
    same = [commit_gate(type("Db", (), {"url": sa_url(u)})()) for u in (url, url, url + "x")]
    assert same[0] is same[1] and same[0] is not same[2]  # one gate per database


def test_merge_evidence_must_be_minus_one_or_metres(tmp_path: Path) -> None:
    """``merge --merge-evidence`` takes the parameter's values only: -1 (the map's scale) or ≥ 0 metres."""
    db = f"sqlite:///{tmp_path / 'e.db'}"
    code, err = cli_code("merge", "--db", db, "--map", "a", "--into", "b", "--merge-evidence", "-3")
    assert code == 2 and "--merge-evidence must be -1 (the map's scale) or at least 0" in err
    code, err = cli_code("merge", "--db", db, "--map", "a", "--into", "b", "--merge-evidence", "0")
    assert code == 2 and "no map named 'a'" in err  # a valid value gets as far as reading the maps


def test_a_merge_the_logs_end_rejects_is_stored_as_the_session_alone(
    tour: Path,
    db_url: str,  # noqa: F811
    make_url: Any,  # noqa: F811
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A probation still running when the log ends is judged there (``OnlineMerger.finish``); when the
    judgement rejects the merge, the store gets the session's own map (the engine that never merged) and a
    ``rejected`` event, in the one final transaction, and session 1's map is untouched."""
    from mapserver.merge import verify

    pipeline.process_into_store(tour / "session1.bag", PARAMS, db_url=db_url)
    before = _snapshot(db_url, "session1")
    monkeypatch.setattr(verify.Probation, "_may_conclude", lambda self, distance: False)  # runs to the log's end
    monkeypatch.setattr(verify.Probation, "conclude_at_end", lambda self, distance: verify.REJECTED)
    run = pipeline.process_into_store(tour / "session2.bag", PARAMS, db_url=db_url)
    assert [m["status"] for m in run.merges] == ["rejected"] and run.map_name == "session2"
    alone = make_url()
    pipeline.process_into_store(tour / "session2.bag", PARAMS, db_url=alone, merge=False)

    def own(url: str) -> dict[str, np.ndarray]:  # session ids differ between the two databases
        return {k: v for k, v in _engine_keys(_snapshot(url, "session2")).items() if not k.endswith("_origin")}

    assert_same_arrays(own(db_url), own(alone))
    assert_same_arrays(before, _snapshot(db_url, "session1"))
    with open_database(db_url) as db, db.read() as conn:
        assert [e.status for e in list_merge_events(conn=conn)] == ["rejected"]


def test_a_merge_kept_when_the_log_ends_in_its_probation_is_listed_as_unverified(
    tour: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The same run with a judgement that keeps the merge: it stands, its verification ``incomplete``, and the
    map's merge counts (``maps --json``, ``GET /v1/maps``) say one merge is unverified."""
    from mapserver.merge import verify

    url = f"sqlite:///{tmp_path / 'kept.db'}"
    pipeline.process_into_store(tour / "session1.bag", PARAMS, db_url=url)
    monkeypatch.setattr(verify.Probation, "_may_conclude", lambda self, distance: False)
    run = pipeline.process_into_store(tour / "session2.bag", PARAMS, db_url=url)
    (merge,) = run.merges
    assert merge["status"] == "applied" and merge["evidence"]["verification"]["status"] == "incomplete"
    assert merge["evidence"]["verification"]["since_match_m"] >= 0.0
    (listed,) = cli_json("maps", "--db", url, "--json")["maps"]
    assert listed["merges"] == {"applied": 1, "undone": 0, "rejected": 0, "unverified": 1}
    assert cli_json("unmerge", "--db", url, "--event", str(merge["event"]))  # a user who doubts it undoes it
    (after,) = [m for m in cli_json("maps", "--db", url, "--json")["maps"] if m["name"] == "session1"]
    assert after["merges"] == {"applied": 0, "undone": 1, "rejected": 0, "unverified": 0}

"""``mapserver process LOG --db``: exact resume in a new process, evidence, no duplicates, clear refusals."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mapserver.cli import main
from mapserver.processing import pipeline
from mapserver.store import load_map, open_database
from mapserver.store.evidence import decode_jpeg, get_evidence
from mapserver.store.sessions import get_reckoning
from tests.mapserver.store.conftest import assert_same_arrays, row_counts, small_params, write_loop_log
from tests.worlds import StripWorld

pytestmark = pytest.mark.slow


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    """Run ``mapserver ARGS`` in a new process."""
    return subprocess.run(
        [sys.executable, "-c", "from mapserver.cli import entry; entry()", *args],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


@pytest.fixture
def loop_log(tmp_path: Path) -> Path:
    return write_loop_log(tmp_path / "loop.bag", laps=1.6)


def test_resuming_in_a_new_process_equals_processing_in_one_go(loop_log: Path, db_url: str, make_url) -> None:  # type: ignore[no-untyped-def]
    params = small_params()
    one_go = pipeline.process_into_store(loop_log, params, db_url=db_url)
    assert one_go.loop_closures > 0
    split_url = make_url()
    first = _cli("process", str(loop_log), "--preset", "irat", "--db", split_url, "--stop-after", "37", "--json")
    assert first.returncode == 0, first.stderr
    assert json.loads(first.stdout.splitlines()[-1])["frames"] == 37
    second = _cli("process", str(loop_log), "--preset", "irat", "--db", split_url, "--json")
    assert second.returncode == 0, second.stderr
    summary = json.loads(second.stdout.splitlines()[-1])
    assert summary["frames"] == one_go.frames
    assert summary["experiences"] == one_go.experiences and summary["links"] == one_go.links
    with open_database(db_url) as a, open_database(split_url) as b:
        whole, resumed = load_map(a, name="loop"), load_map(b, name="loop")
        assert_same_arrays(whole.snapshot, resumed.snapshot)  # same session id 1 in both databases
        assert [s.frames_processed for s in resumed.meta.sessions] == [one_go.frames]
        assert [s.status for s in resumed.meta.sessions] == ["complete"]
        assert row_counts(a) == row_counts(b)
        with a.read() as ca, b.read() as cb:
            rows_a, pose_a = get_reckoning(conn=ca, session_id=whole.meta.sessions[0].id)
            rows_b, pose_b = get_reckoning(conn=cb, session_id=resumed.meta.sessions[0].id)
        assert rows_a.shape == (one_go.frames, 4)
        assert rows_a.tobytes() == rows_b.tobytes() and pose_a == pose_b


def test_every_experience_has_its_frame_as_evidence(loop_log: Path, db_url: str) -> None:
    params = small_params()
    result = pipeline.process_into_store(loop_log, params, db_url=db_url)
    world = StripWorld(seed=3)
    with open_database(db_url) as db:
        content = load_map(db, name="loop")
        stamps = content.snapshot["em_stamp"]
        t0 = stamps[0]
        with db.read() as conn:
            for exp in range(result.experiences):
                ev = get_evidence(conn=conn, map_id=content.meta.map.id, experience=exp)
                assert ev.offset_s == 0.0 and ev.frame_stamp == stamps[exp]
                pixels = decode_jpeg(ev.data)
                expected = world.view(float(stamps[exp] - t0))  # 1 m/s: arc length = time since start
                assert pixels.shape == expected.shape == (ev.height, ev.width)
                assert np.abs(pixels.astype(float) - expected).mean() < 6.0


def test_a_complete_log_is_answered_with_its_session(loop_log: Path, db_url: str) -> None:
    first = _cli("process", str(loop_log), "--preset", "irat", "--db", db_url, "--json")
    assert first.returncode == 0, first.stderr
    again = _cli("process", str(loop_log), "--preset", "irat", "--db", db_url, "--json")
    assert again.returncode == 0, again.stderr
    assert "stored already as session 'loop' of map 'loop'" in again.stderr
    a, b = (json.loads(r.stdout.splitlines()[-1]) for r in (first, again))
    assert {k: a[k] for k in ("frames", "templates", "experiences", "links", "loop_closures", "map")} == {
        k: b[k] for k in ("frames", "templates", "experiences", "links", "loop_closures", "map")
    }
    with open_database(db_url) as db:
        counts = row_counts(db)
    assert counts["sessions"] == 1 and counts["maps"] == 1


def test_refusals_are_one_line_exit_2(loop_log: Path, tmp_path: Path, db_url: str, capsys) -> None:  # type: ignore[no-untyped-def]
    assert main(["process", str(loop_log), "--preset", "irat", "--db", db_url, "--stop-after", "10"]) == 0
    capsys.readouterr()
    other = write_loop_log(tmp_path / "other.bag", laps=0.6, seed=9)
    assert main(["process", str(other), "--preset", "irat", "--db", db_url, "--map", "loop"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (
        "ERROR: a map named 'loop' already exists and this log is not one of its sessions; choose another map name"
    )
    assert main(["process", str(loop_log), "--preset", "circle", "--db", db_url]) == 2
    assert "stored already as session 'loop' with other parameters" in capsys.readouterr().err
    assert main(["process", str(loop_log), "--preset", "irat", "--db", db_url, "--map", "elsewhere"]) == 2
    assert "cannot be stored in map 'elsewhere'" in capsys.readouterr().err
    assert main(["maps", "--db", db_url, "--json"]) == 0
    maps = json.loads(capsys.readouterr().out.splitlines()[-1])["maps"]
    assert [(m["name"], m["sessions"]) for m in maps] == [("loop", 1)]


def test_a_session_stored_before_a_parameter_existed_continues_with_its_default(
    loop_log: Path,
    db_url: str,
) -> None:
    """A partial session whose stored parameters lack a key added since (here ``merge_sv_enable_f1_gate``,
    added on 2026-11-25) resumes: the missing key takes its default, which is what the session was run with."""
    from sqlalchemy import text

    assert main(["process", str(loop_log), "--preset", "irat", "--db", db_url, "--stop-after", "10"]) == 0
    with open_database(db_url) as db, db.write() as conn:
        (raw,) = conn.execute(text("SELECT params FROM sessions")).one()
        stored = json.loads(raw) if isinstance(raw, str) else dict(raw)
        del stored["merge_sv_enable_f1_gate"]
        conn.execute(text("UPDATE sessions SET params = :p"), {"p": json.dumps(stored)})
    assert main(["process", str(loop_log), "--preset", "irat", "--db", db_url]) == 0
    stored["pc_dim_xy"] = 7  # a parameter that did exist, stored otherwise: still refused
    with open_database(db_url) as db, db.write() as conn:
        conn.execute(text("UPDATE sessions SET params = :p"), {"p": json.dumps(stored)})
    assert main(["process", str(loop_log), "--preset", "irat", "--db", db_url]) == 2


def test_a_session_keeps_when_its_processing_started_and_finished(loop_log: Path, db_url: str) -> None:
    """started_at is taken before the first frame (must: before finished_at), finished_at when it is stored."""
    from mapserver.store import utcnow

    before = utcnow()
    result = pipeline.process_into_store(loop_log, small_params(), db_url=db_url)
    after = utcnow()
    with open_database(db_url) as db:
        session = load_map(db, name="loop").meta.sessions[0]
    assert before <= session.started_at < session.finished_at <= after
    spent = (session.finished_at - session.started_at).total_seconds()
    assert session.frames_per_s == pytest.approx(result.frames / spent)
    assert spent >= 0.5 * result.seconds  # the processing itself lies between the two

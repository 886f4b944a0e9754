"""Upload housekeeping (issue 61, item 6): leftovers of killed servers and the retention of processed uploads.

Paired: an old done or failed job's upload is removed (by the server's policy and by ``uploads prune``) —
a queued or running job's upload never is, nor a finished one younger than the policy, nor anything of
another database; a leftover nobody names is removed — a fresh one, which a live server may be writing,
is not.
"""

from __future__ import annotations

import json
import os
import secrets
import time
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any

import pytest
import sqlalchemy as sa

from mapserver.api.housekeeping import LEFTOVER_GRACE_S, prune_uploads, remove_leftovers
from mapserver.cli import main
from mapserver.store import Database, open_database
from mapserver.store.jobs import create_job
from mapserver.store.models import Job, utcnow

DAY = 86400.0


@dataclass
class Seeded:
    """A database and an upload directory with one folder per job (name → folder)."""

    url: str
    root: Path
    folders: dict[str, Path]
    ids: dict[str, int]


def _folder(root: Path, size: int = 1000) -> tuple[Path, Path]:
    folder = root / secrets.token_hex(8)
    log = folder / "log" / "x.bag"
    log.parent.mkdir(parents=True)
    log.write_bytes(os.urandom(size))
    return folder, log


def _seed(db: Database, root: Path, *, share: bool = True) -> Seeded:
    """Jobs: done/failed 10 days ago, done 1 day ago, queued and running (10 days old), an old done job whose
    upload lies outside the directory and (``share``) an old done job in the queued job's folder."""
    now = utcnow()
    folders: dict[str, Path] = {}
    ids: dict[str, int] = {}
    plan = {"old_done": ("done", 10), "old_failed": ("failed", 10), "young_done": ("done", 1),
            "queued": ("queued", None), "running": ("running", None)}  # fmt: skip
    with db.write() as conn:
        for name, (status, age) in plan.items():
            folders[name], log = _folder(root)
            ids[name] = create_job(conn=conn, upload_path=str(log), map_name=name).id
            if status == "running":
                conn.execute(sa.update(Job).where(Job.id == ids[name]).values(status=status, lease_token=1))
            elif status != "queued":
                conn.execute(sa.update(Job).where(Job.id == ids[name])
                             .values(status=status, finished_at=now - timedelta(days=age)))  # fmt: skip
            conn.execute(sa.update(Job).where(Job.id == ids[name]).values(created_at=now - timedelta(days=10)))
        outside = root.parent / "elsewhere" / "x.bag"
        outside.parent.mkdir(parents=True, exist_ok=True)
        outside.write_bytes(b"x")
        ids["outside"] = create_job(conn=conn, upload_path=str(outside)).id
        if share:
            ids["shares_queued"] = create_job(conn=conn, upload_path=str(folders["queued"] / "log" / "y.bag")).id
        for name in ("shares_queued", "outside"):
            conn.execute(sa.update(Job).where(Job.id == ids.get(name, -1))
                         .values(status="done", finished_at=now - timedelta(days=10)))  # fmt: skip
    return Seeded(str(db.url), root, folders, ids)


@pytest.fixture
def seeded(tmp_path: Path) -> Any:
    url = f"sqlite:///{tmp_path / 'api.db'}"
    with open_database(url) as db:
        yield db, _seed(db, tmp_path / "uploads")


def test_retention_removes_old_finished_uploads_and_never_a_live_jobs(seeded: Any) -> None:
    db, s = seeded
    removed = prune_uploads(db, s.root, keep_s=7 * DAY)
    assert sorted((r.job, r.status) for r in removed) == [(s.ids["old_done"], "done"), (s.ids["old_failed"], "failed")]
    assert all(r.bytes == 1000 for r in removed)
    assert not s.folders["old_done"].exists() and not s.folders["old_failed"].exists()
    for kept in ("young_done", "queued", "running"):  # younger than the policy; live jobs, whatever their age
        assert (s.folders[kept] / "log" / "x.bag").is_file(), kept
    assert (s.root.parent / "elsewhere" / "x.bag").is_file()  # outside the upload directory: not ours
    assert prune_uploads(db, s.root, keep_s=7 * DAY) == []  # nothing more to do
    assert prune_uploads(db, s.root, keep_s=float("inf")) == []  # inf keeps everything
    removed = prune_uploads(db, s.root, keep_s=0.0)
    assert [r.job for r in removed] == [s.ids["young_done"]]
    assert s.folders["queued"].is_dir() and s.folders["running"].is_dir()


def test_uploads_prune_command(seeded: Any, capsys: pytest.CaptureFixture[str]) -> None:
    _db, s = seeded
    argv = ["uploads", "prune", "--db", s.url, "--upload-dir", str(s.root), "--json"]
    assert main([*argv, "--older-than", "30"]) == 0
    first = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (first["removed"], first["leftovers"], first["bytes"]) == ([], [], 0)
    assert main([*argv, "--older-than", "7"]) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out.strip().splitlines()[-1])
    assert sorted(r["job"] for r in result["removed"]) == sorted([s.ids["old_done"], s.ids["old_failed"]])
    assert (result["bytes"], result["older_than_days"], result["upload_dir"]) == (2000, 7.0, str(s.root))
    assert "removed 2 upload(s)" in captured.err
    assert s.folders["queued"].is_dir() and s.folders["running"].is_dir() and s.folders["young_done"].is_dir()
    assert main(["uploads", "prune", "--db", s.url, "--older-than", "-1"]) == 2  # bad input: one line, exit 2
    assert capsys.readouterr().err.startswith("ERROR: --older-than")


def _age(path: Path, seconds: float) -> None:
    when = time.time() - seconds
    for top, dirs, files in os.walk(path):
        for name in (*dirs, *files):
            os.utime(os.path.join(top, name), (when, when))
    os.utime(path, (when, when))


def test_leftovers_go_after_the_grace_and_never_a_jobs_folder(seeded: Any) -> None:
    db, s = seeded
    assert remove_leftovers(db, s.root, grace_s=0.0) == []  # the first cleanup only marks the directory
    staging = s.root / ".incoming"
    staging.mkdir()
    part = staging / "abc.part"
    part.write_bytes(b"x" * 5000)
    orphan, _log = _folder(s.root, 7000)
    assert remove_leftovers(db, s.root, grace_s=LEFTOVER_GRACE_S) == []  # fresh: a live server may write them
    _age(part, 2 * LEFTOVER_GRACE_S)
    _age(orphan, 2 * LEFTOVER_GRACE_S)
    for name in s.folders:
        _age(s.folders[name], 2 * LEFTOVER_GRACE_S)
    removed = remove_leftovers(db, s.root, grace_s=LEFTOVER_GRACE_S)
    assert sorted((Path(r.path).name, r.bytes) for r in removed) == sorted([(part.name, 5000), (orphan.name, 7000)])
    assert all(folder.is_dir() for folder in s.folders.values())  # every job's folder stays, whatever its status


def test_a_directory_shared_with_another_database_keeps_its_leftovers(seeded: Any, tmp_path: Path) -> None:
    db, s = seeded
    assert remove_leftovers(db, s.root, grace_s=0.0) == []  # the first cleanup marks the directory as db's
    orphan, _log = _folder(s.root)
    with open_database(f"sqlite:///{tmp_path / 'other.db'}") as other:
        assert remove_leftovers(other, s.root, grace_s=0.0) == []  # the directory is marked as the first's
    assert orphan.is_dir() and all(folder.is_dir() for folder in s.folders.values())
    assert [Path(r.path).name for r in remove_leftovers(db, s.root, grace_s=0.0)] == [orphan.name]


def test_the_server_removes_leftovers_at_start_and_applies_the_policy(tmp_path: Path, make_api: Any) -> None:
    make_api().client.__exit__(None, None, None)  # an earlier run of the server marked its upload directory
    db = open_database(f"sqlite:///{tmp_path / 'api.db'}")  # make_api's database and upload directory
    s = _seed(db, tmp_path / "uploads", share=False)  # its engine runs the queued jobs: they fail, kept 7 days
    staging = s.root / ".incoming"
    staging.mkdir(exist_ok=True)
    (staging / "killed.part").write_bytes(b"x" * 5000)
    orphan, _log = _folder(s.root, 7000)  # half-unpacked by a killed server: no job names it
    db.dispose()
    api = make_api(keep_uploads_days=7.0)
    assert not (staging / "killed.part").exists() and not orphan.exists()  # gone before the engine started
    deadline = time.monotonic() + 10
    while (s.folders["old_done"].exists() or s.folders["old_failed"].exists()) and time.monotonic() < deadline:
        time.sleep(0.05)  # the retention's first sweep runs in its own thread
    assert not s.folders["old_done"].exists() and not s.folders["old_failed"].exists()
    for kept in ("young_done", "queued", "running"):
        assert s.folders[kept].is_dir(), kept
    assert api.client.get("/healthz").status_code == 200

"""One upload, one read: the log's identity is read when the upload is checked and handed on to the job.

Counted with the reader's own functions wrapped: ``_topic_infos`` runs once per :func:`open_log` (the index
read), the ``sha256`` property hashes when its cache is empty, ``Database`` is made once per pool.
"""

from __future__ import annotations

import hashlib
import tarfile
from collections import Counter
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from mapserver.api.worker import job_identity
from mapserver.ingest import LogIdentity, open_log
from mapserver.ingest import reader as log_reader
from mapserver.store import db as store_db
from mapserver.store import find_session, open_database
from tests.mapserver.api.conftest import Api
from tests.mapserver.api.logs import write_strip_log


@pytest.fixture
def counts(monkeypatch: pytest.MonkeyPatch) -> Counter[str]:
    """Count log index reads (one per open_log), SHA-256 computations and Database objects made."""
    seen: Counter[str] = Counter()
    infos, digest, made = log_reader._topic_infos, log_reader.MissionLog.sha256.fget, store_db.Database.__init__
    assert digest is not None

    def read_index(*args: Any, **kwargs: Any) -> Any:
        seen["open_log"] += 1
        return infos(*args, **kwargs)

    def sha256(self: Any) -> str:
        seen["sha256"] += self._sha256 is None
        return digest(self)

    def database(self: Any, *args: Any, **kwargs: Any) -> None:
        seen["database"] += 1
        made(self, *args, **kwargs)

    monkeypatch.setattr(log_reader, "_topic_infos", read_index)
    monkeypatch.setattr(log_reader.MissionLog, "sha256", property(sha256))
    monkeypatch.setattr(store_db.Database, "__init__", database)
    return seen


def _stored(api: Api, sha256: str, mapping: dict[str, Any]) -> bool:
    with open_database(api.db_url) as db, db.read() as conn:
        return find_session(conn=conn, log_sha256=sha256, topics=mapping) is not None


def test_an_uploaded_log_is_hashed_as_it_streams_in_and_read_once_for_its_identity(
    api: Api, strip_log: Path, counts: Counter[str]
) -> None:
    response = api.upload(strip_log, preset="irat")
    assert response.status_code == 202, response.text
    job = api.wait(response.json()["job"])
    assert job["status"] == "done", job
    # the index is read twice: the upload's check, the job's run; the log is not hashed after the upload;
    # the job writes through the server's database (no second pool)
    assert counts == {"open_log": 2}
    expected = hashlib.sha256(strip_log.read_bytes()).hexdigest()  # independent: the file's bytes
    assert response.json()["sha256"] == expected and response.json()["frames"] == 62
    with open_log(strip_log) as log:
        mapping = log.mapping.as_dict()
    assert _stored(api, expected, mapping)


def test_an_unpacked_log_is_hashed_once_at_upload(api: Api, tmp_path: Path, counts: Counter[str]) -> None:
    bag_dir = write_strip_log(tmp_path / "logs" / "rosbag2_mission", fmt="db3", directory=True)
    archive = tmp_path / "mission.tar.gz"
    with tarfile.open(archive, "w:gz") as tf:
        tf.add(bag_dir, arcname=bag_dir.name)
    response = api.upload(archive, preset="irat")
    assert response.status_code == 202, response.text
    assert api.wait(response.json()["job"])["status"] == "done"
    assert counts == {"open_log": 2, "sha256": 1}  # the unpacked directory: its files hashed once, at upload
    digest = hashlib.sha256()  # independent: the directory's files in sorted order
    for file in sorted(p for p in bag_dir.rglob("*") if p.is_file()):
        digest.update(file.read_bytes())
    with open_log(bag_dir) as log:
        mapping = log.mapping.as_dict()
    assert _stored(api, digest.hexdigest(), mapping)


def test_a_job_reads_the_recorded_identity_or_the_log_when_none_was_recorded(strip_log: Path) -> None:
    recorded = LogIdentity(sha256="ab" * 32, mapping={"image": "/cam"}, frames=7)
    job: Any = SimpleNamespace(options={"log": recorded.as_dict()}, topics=None)
    assert job_identity(job, strip_log.with_name("gone.bag")) == recorded  # the log is not opened
    older: Any = SimpleNamespace(options={"frames": 62}, topics=None)  # queued before identities were recorded
    read = job_identity(older, strip_log)
    assert read.sha256 == hashlib.sha256(strip_log.read_bytes()).hexdigest() and read.frames == 62
    assert LogIdentity.from_dict({"sha256": "x", "frames": 3}) is None  # incomplete: no mapping

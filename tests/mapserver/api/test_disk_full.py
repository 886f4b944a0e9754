"""A full disk while receiving or unpacking an upload is 507 — the server's fault, never the client's 400.

Paired: ``ENOSPC`` → 507 with a REST-worded body and an operator log line, for a bag and for an archive;
another failure of the server's files (``EIO``) → 500 without internals (never 400); once there is room
again the same upload is accepted. The real thing runs on a 2 MiB tmpfs when the tests may mount one.
"""

from __future__ import annotations

import errno
import logging
import os
import subprocess
import tarfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from mapserver.api.errors import STORAGE_FULL_DETAIL
from tests.mapserver.api.conftest import Api
from tests.mapserver.api.logs import write_strip_log

REAL_OPEN = Path.open


class FailingFile:
    """A file opened for writing whose writes fail with ``code`` once ``after`` bytes went through."""

    def __init__(self, handle: Any, code: int, after: int) -> None:
        self.handle, self.code, self.after, self.written = handle, code, after, 0

    def write(self, data: bytes) -> int:
        if self.written + len(data) > self.after:
            raise OSError(self.code, os.strerror(self.code))
        self.written += len(data)
        return int(self.handle.write(data))

    @property
    def closed(self) -> bool:
        return bool(self.handle.closed)

    def close(self) -> None:
        self.handle.close()

    def __enter__(self) -> FailingFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def fail_writes(monkeypatch: pytest.MonkeyPatch, code: int, where: Callable[[Path], bool], after: int = 4096) -> None:
    """Make new files (mode ``xb``, as staging and unpacking open them) for which ``where`` holds fail."""

    def open_(self: Path, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
        handle = REAL_OPEN(self, mode, *args, **kwargs)
        return FailingFile(handle, code, after) if mode == "xb" and where(self) else handle

    monkeypatch.setattr(Path, "open", open_)


def _staged(path: Path) -> bool:
    return path.suffix == ".part"


def _unpacked(path: Path) -> bool:
    return path.suffix != ".part"


def _kept(api: Api) -> list[Path]:
    return sorted(p for p in api.settings.uploads.rglob("*") if p.is_file())


def _jobs(api: Api) -> int:
    from mapserver.store import open_database
    from mapserver.store.jobs import count_jobs

    with open_database(api.db_url) as db, db.read() as conn:
        return sum(count_jobs(conn=conn).values())


@pytest.fixture
def tarred(tmp_path: Path) -> Path:
    """A tar archive holding one strip log (a plain tar: the archive is as large as what it unpacks to)."""
    log = write_strip_log(tmp_path / "logs" / "tarred.bag", laps=4.0, width=256)
    archive = tmp_path / "archives" / "mission.tar"
    archive.parent.mkdir()
    with tarfile.open(archive, "w") as tf:
        tf.add(log, arcname=log.name)
    return archive


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EDQUOT], ids=["ENOSPC", "EDQUOT"])
def test_full_disk_while_receiving_a_bag_is_507(api: Api, strip_log: Path, monkeypatch: pytest.MonkeyPatch,
                                                caplog: pytest.LogCaptureFixture, code: int) -> None:  # fmt: skip
    fail_writes(monkeypatch, code, _staged)
    with caplog.at_level(logging.ERROR, logger="mapserver.api.errors"):
        response = api.upload(strip_log, preset="irat")
    assert (response.status_code, response.json()) == (507, {"detail": STORAGE_FULL_DETAIL})
    assert _kept(api) == [] and _jobs(api) == 0  # the partial staged file is gone
    (line,) = [r.getMessage() for r in caplog.records if "disk full" in r.getMessage()]
    assert "receiving an upload" in line and str(api.settings.uploads) in line and "bytes free" in line
    monkeypatch.undo()  # room again: the same upload is accepted
    assert api.upload(strip_log, preset="irat").status_code == 202


def test_full_disk_while_unpacking_an_archive_is_507_not_400(api: Api, tarred: Path,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:  # fmt: skip
    fail_writes(monkeypatch, errno.ENOSPC, _unpacked)
    response = api.upload(tarred, preset="irat")
    assert (response.status_code, response.json()) == (507, {"detail": STORAGE_FULL_DETAIL})
    assert _kept(api) == [] and _jobs(api) == 0  # neither the staged archive nor the half-unpacked folder
    monkeypatch.undo()
    assert api.upload(tarred, preset="irat").status_code == 202


@pytest.mark.parametrize("what", ["bag", "archive"])
def test_another_failure_of_the_servers_files_is_500_without_internals(
    api: Api, strip_log: Path, tarred: Path, monkeypatch: pytest.MonkeyPatch, what: str
) -> None:
    fail_writes(monkeypatch, errno.EIO, _staged if what == "bag" else _unpacked)
    response = api.upload(strip_log if what == "bag" else tarred, preset="irat")
    detail = response.json()["detail"]
    assert response.status_code == 500, response.text  # the server's fault: never a 400 for the client
    assert detail.startswith("internal error")
    for internal in (os.strerror(errno.EIO), str(api.settings.uploads), "Errno", "Traceback"):
        assert internal not in detail
    assert _kept(api) == [] and _jobs(api) == 0


# ------------------------------------------------------------------------------- a real full disk (tmpfs)
@pytest.fixture
def tiny_uploads(tmp_path: Path) -> Iterator[Path]:
    """``tmp_path/uploads`` on a 2 MiB tmpfs (skipped where the tests may not mount one)."""
    target = tmp_path / "uploads"
    target.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(target)],
                             capture_output=True, check=False)  # fmt: skip
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {mounted.stderr.decode(errors='replace').strip()}")
    try:
        yield target
    finally:
        subprocess.run(["umount", "-l", str(target)], check=False)


def test_a_real_full_disk_is_507_for_a_bag_and_an_archive(tiny_uploads: Path, make_api: Any, tmp_path: Path,
                                                          tarred: Path) -> None:  # fmt: skip
    api: Api = make_api()
    big = write_strip_log(tmp_path / "logs" / "big.bag", laps=30.0)  # 7.6 MB: the staging fills the disk
    small = write_strip_log(tmp_path / "logs" / "small.bag")  # 0.3 MB: fits
    assert big.stat().st_size > 2 << 20  # the staging alone fills the disk
    assert tarred.stat().st_size < 2 << 20 < 2 * tarred.stat().st_size  # the archive fits; it and its contents do not
    response = api.upload(big, preset="irat")
    assert (response.status_code, response.json()) == (507, {"detail": STORAGE_FULL_DETAIL})
    response = api.upload(tarred, preset="irat")  # staged whole; unpacking it needs the same again
    assert (response.status_code, response.json()) == (507, {"detail": STORAGE_FULL_DETAIL})
    assert _kept(api) == []  # the disk is as empty as before: no staged file, no half-unpacked folder
    response = api.upload(small, preset="irat")
    assert response.status_code == 202, response.text
    assert api.wait(response.json()["job"])["status"] == "done"

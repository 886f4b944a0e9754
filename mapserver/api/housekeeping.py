"""The upload directory's housekeeping: leftovers of killed servers, and the retention of processed uploads.

Layout (``Settings.uploads``): ``.incoming/*.part`` are uploads being received; each accepted upload has
its own folder ``<hex>/`` (the log file, or the unpacked archive) named by its job's ``upload_path``.

* Leftovers (:func:`remove_leftovers`): ``.part`` files and hex-named folders that no job of the database
  names — what a server killed while receiving or unpacking an upload left behind. A server that holds the
  database's server lock removes them all at start (no request runs yet, no other server writes there);
  otherwise (replicas sharing the directory, ``uploads prune``) only those untouched for
  :data:`LEFTOVER_GRACE_S`, since a live server may be writing them.
* Retention (:func:`prune_uploads`): the folder of a job that finished (``done`` or ``failed``) more than
  ``keep_s`` ago is removed, unless a queued or running job names the same folder. Queued and running
  jobs' folders are never removed.

The directory may be shared by servers of *other* databases (two SQLite files in one directory share the
default ``uploads/``), whose jobs this database does not know: the first cleanup marks the directory with
an empty folder ``.owner-<hash of the database's identity>`` (a folder, so nothing counts it as a file)
and removes nothing that time (what is there may be another database's); leftovers are removed only
while that is the one owner mark (retention is safe either way: it removes only folders this database's
jobs name).
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import shutil
import threading
import time
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

from mapserver.store import Database, utcnow
from mapserver.store.db import sqlite_database_file
from mapserver.store.jobs import job_uploads

logger = logging.getLogger(__name__)

STAGING = ".incoming"
OWNER_PREFIX = ".owner-"
LEFTOVER_GRACE_S = 3600.0
"""A leftover untouched this long is removed even while other servers may be running (seconds)."""
SWEEP_INTERVAL_S = 3600.0
"""A running server applies the retention and removes old leftovers this often (seconds)."""
FINISHED = ("done", "failed")
LIVE = ("queued", "running")
_FOLDER = re.compile(r"[0-9a-f]{8,64}")


@dataclass(frozen=True, slots=True)
class Removed:
    """One removed file or folder: its path, its bytes, and the job it belonged to (None for a leftover)."""

    path: str
    bytes: int
    job: int | None = None
    status: str | None = None

    def as_dict(self) -> dict[str, object]:
        """Return the JSON form (``uploads prune --json``)."""
        return {"path": self.path, "bytes": self.bytes, "job": self.job, "status": self.status}


def upload_folder(upload_path: str, root: Path) -> Path | None:
    """Return the upload's own folder (the hex-named directory right under ``root`` holding it), or None."""
    base = root.resolve()
    try:
        relative = Path(upload_path).resolve().relative_to(base)
    except ValueError:
        return None
    if len(relative.parts) < 2 or not _FOLDER.fullmatch(relative.parts[0]):
        return None
    return base / relative.parts[0]


def _tree(path: Path) -> tuple[int, float]:
    """Return the bytes under ``path`` and the newest modification time in it (links not followed)."""
    total, newest = 0, path.lstat().st_mtime
    for top, dirs, files in os.walk(path):
        for name in (*dirs, *files):
            try:
                info = os.lstat(os.path.join(top, name))
            except FileNotFoundError:
                continue
            total += info.st_size if name in files else 0
            newest = max(newest, info.st_mtime)
    return total, newest


def database_identity(db: Database) -> str:
    """Return the database's identity in the upload directory: its resolved file, or its URL without password."""
    database = sqlite_database_file(db.url)
    return f"sqlite:{database.resolve()}" if database is not None else db.display_url()


def owns_directory(db: Database, root: Path) -> bool:
    """Return whether ``root`` is marked as ``db``'s; mark it when nobody has (False that time); log otherwise."""
    mine = OWNER_PREFIX + hashlib.sha256(database_identity(db).encode()).hexdigest()[:16]
    marks = sorted(p.name for p in root.glob(OWNER_PREFIX + "*"))
    if marks == [mine]:
        return True
    if marks:
        logger.warning("the upload directory %s is shared with another database (%s): leftovers are not removed",
                       root, ", ".join(m for m in marks if m != mine))  # fmt: skip
        return False
    try:
        (root / mine).mkdir(exist_ok=True)
    except OSError as err:
        logger.warning("cannot mark the upload directory %s as this database's: %s", root, err)
    else:
        logger.info("marked the upload directory %s as this database's; leftovers go from the next cleanup", root)
    return False


def remove_leftovers(db: Database, root: Path, *, grace_s: float) -> list[Removed]:
    """Remove staged ``.part`` files and folders no job names, untouched for ``grace_s`` seconds (see module)."""
    if not root.is_dir() or not owns_directory(db, root):
        return []
    cutoff = time.time() - grace_s
    removed: list[Removed] = []
    for part in sorted((root / STAGING).glob("*.part")):
        try:
            info = part.lstat()
        except FileNotFoundError:
            continue
        if info.st_mtime <= cutoff:
            part.unlink(missing_ok=True)
            removed.append(Removed(str(part), info.st_size))
    with db.read() as conn:
        named = {upload_folder(path, root) for _id, _status, path in job_uploads(conn=conn)}
    for child in sorted(root.iterdir()):
        if not _FOLDER.fullmatch(child.name) or child.is_symlink() or not child.is_dir():
            continue
        if child.resolve() in named:
            continue
        size, newest = _tree(child)
        if newest <= cutoff:
            shutil.rmtree(child, ignore_errors=True)
            removed.append(Removed(str(child), size))
    return removed


def prune_uploads(db: Database, root: Path, *, keep_s: float) -> list[Removed]:
    """Remove the folders of jobs that finished more than ``keep_s`` seconds ago (never a live job's)."""
    if keep_s == float("inf") or not root.is_dir():
        return []
    before = utcnow() - timedelta(seconds=keep_s)
    with db.read() as conn:
        finished = job_uploads(conn=conn, statuses=FINISHED, finished_before=before)
        live = {upload_folder(path, root) for _id, _status, path in job_uploads(conn=conn, statuses=LIVE)}
    removed: list[Removed] = []
    for job_id, status, path in finished:
        folder = upload_folder(path, root)
        if folder is None or folder in live or not folder.is_dir():
            continue
        size, _newest = _tree(folder)
        shutil.rmtree(folder, ignore_errors=True)
        removed.append(Removed(str(folder), size, job_id, status))
    return removed


def describe(removed: list[Removed]) -> str:
    """Return ``N (B bytes)`` for a log line."""
    return f"{len(removed)} ({sum(r.bytes for r in removed)} bytes)"


class Janitor:
    """A thread that applies the retention and removes old leftovers now and every :data:`SWEEP_INTERVAL_S`.

    Args:
        db: the map store.
        root: the upload directory.
        keep_s: a finished job's upload is kept this long (``inf``: forever).
    """

    def __init__(self, db: Database, root: Path, *, keep_s: float, interval_s: float = SWEEP_INTERVAL_S) -> None:
        self.db = db
        self.root = root
        self.keep_s = keep_s
        self.interval_s = interval_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def sweep(self) -> list[Removed]:
        """Remove old leftovers and expired uploads once; log what went; return it."""
        leftovers = remove_leftovers(self.db, self.root, grace_s=LEFTOVER_GRACE_S)
        expired = prune_uploads(self.db, self.root, keep_s=self.keep_s)
        if leftovers:
            logger.warning("removed leftover uploads %s", describe(leftovers))
        if expired:
            days = self.keep_s / 86400
            logger.info("removed the uploads of jobs finished more than %g days ago: %s", days, describe(expired))
        return leftovers + expired

    def start(self) -> None:
        """Start the thread (its first sweep runs at once)."""
        self._thread = threading.Thread(target=self._loop, name="mapserver-uploads", daemon=True)
        self._thread.start()

    def stop(self, timeout: float | None = 10.0) -> None:
        """Stop the thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self.sweep()
            except Exception as err:  # the database or the disk failed: try again at the next sweep
                logger.error("upload housekeeping failed: %s", err)
            self._stop.wait(self.interval_s)

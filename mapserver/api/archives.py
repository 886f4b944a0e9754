"""Safe unpacking of ROS 2 bag directories uploaded as ``.zip`` or ``.tar`` archives.

Only regular files and directories are unpacked. An entry with an absolute path, a drive letter, a
backslash or a ``..`` component, a symbolic or hard link, a device, FIFO or any other special file
refuses the whole archive (nothing is kept), and so do encrypted zip entries, more than
``max_members`` entries or more than ``max_bytes`` unpacked bytes — counted while copying, never
trusted from the archive's headers (zip bombs stop at the limit).
"""

from __future__ import annotations

import shutil
import stat
import tarfile
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path, PurePosixPath
from typing import IO

from mapserver.errors import InputError

ARCHIVE_SUFFIXES: tuple[str, ...] = (".zip", ".tar", ".tar.gz", ".tgz", ".tar.bz2", ".tar.xz")
_COPY_CHUNK = 1 << 20


def archive_suffix(filename: str) -> str | None:
    """Return the archive suffix of ``filename`` (``.tar.gz``, ``.zip``, ...) or None."""
    lower = filename.lower()
    return next((s for s in sorted(ARCHIVE_SUFFIXES, key=len, reverse=True) if lower.endswith(s)), None)


def _member_path(name: str, dest: Path) -> Path:
    """Return where entry ``name`` goes inside ``dest``; refuse anything that could leave it."""
    if not name or "\\" in name or "\x00" in name:
        msg = f"archive entry {name!r} has an unsafe name"
        raise InputError(msg)
    pure = PurePosixPath(name)
    if pure.is_absolute() or name.startswith("/") or (pure.parts and ":" in pure.parts[0]):
        msg = f"archive entry {name!r} has an absolute path"
        raise InputError(msg)
    if any(part == ".." for part in pure.parts):
        msg = f"archive entry {name!r} leaves the archive's directory ('..')"
        raise InputError(msg)
    parts = [p for p in pure.parts if p not in ("", ".")]
    target = dest.joinpath(*parts) if parts else dest
    resolved = target.resolve()
    root = dest.resolve()
    if resolved != root and root not in resolved.parents:
        msg = f"archive entry {name!r} leaves the archive's directory"
        raise InputError(msg)
    return target


class _Budget:
    def __init__(self, max_bytes: int, max_members: int) -> None:
        self.max_bytes = max_bytes
        self.max_members = max_members
        self.bytes = 0
        self.members = 0

    def member(self) -> None:
        self.members += 1
        if self.members > self.max_members:
            msg = f"archive has more than {self.max_members} entries"
            raise InputError(msg)

    def copy(self, source: IO[bytes], target: Path) -> None:
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            handle = target.open("xb")
        except FileExistsError as err:
            msg = f"archive holds {target.name!r} twice"
            raise InputError(msg) from err
        with handle:
            while chunk := source.read(_COPY_CHUNK):
                self.bytes += len(chunk)
                if self.bytes > self.max_bytes:
                    msg = f"archive unpacks to more than the server's limit of {self.max_bytes} bytes"
                    raise InputError(msg)
                handle.write(chunk)


def _unzip(archive: Path, dest: Path, budget: _Budget) -> None:
    with zipfile.ZipFile(archive) as zf:
        infos = zf.infolist()
        if len(infos) > budget.max_members:
            msg = f"archive has {len(infos)} entries, more than {budget.max_members}"
            raise InputError(msg)
        declared = sum(i.file_size for i in infos)
        if declared > budget.max_bytes:
            msg = f"archive declares {declared} unpacked bytes, more than the server's limit of {budget.max_bytes}"
            raise InputError(msg)
        for info in infos:
            budget.member()
            target = _member_path(info.filename, dest)
            mode = info.external_attr >> 16  # Unix mode when the creator stored one (type bits 0 otherwise)
            if stat.S_IFMT(mode) not in (0, stat.S_IFREG, stat.S_IFDIR):
                kind = "a symbolic link" if stat.S_ISLNK(mode) else "a special file"
                msg = f"archive entry {info.filename!r} is {kind}; only files and directories are accepted"
                raise InputError(msg)
            if info.flag_bits & 0x1:
                msg = f"archive entry {info.filename!r} is encrypted"
                raise InputError(msg)
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            with zf.open(info) as source:
                budget.copy(source, target)


def _untar(archive: Path, dest: Path, budget: _Budget) -> None:
    with tarfile.open(archive, mode="r:*") as tf:
        for member in tf:
            budget.member()
            target = _member_path(member.name, dest)
            if member.isdir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            if not member.isreg():
                kind = "a link" if (member.issym() or member.islnk()) else "a special file"
                msg = f"archive entry {member.name!r} is {kind}; only files and directories are accepted"
                raise InputError(msg)
            source = tf.extractfile(member)
            if source is None:  # pragma: no cover - isreg() members always have data
                msg = f"archive entry {member.name!r} has no data"
                raise InputError(msg)
            with source:
                budget.copy(source, target)


@contextmanager
def _clean_on_error(dest: Path) -> Iterator[None]:
    try:
        yield
    except BaseException:
        shutil.rmtree(dest, ignore_errors=True)
        raise


def extract_archive(archive: Path, dest: Path, *, kind: str, max_bytes: int, max_members: int) -> None:
    """Unpack ``archive`` (``kind`` from :func:`archive_suffix`) into the new directory ``dest``.

    Raises:
        InputError: unreadable archive or an unsafe entry (see the module docstring); ``dest`` is removed.
    """
    dest.mkdir(parents=True, exist_ok=False)
    budget = _Budget(max_bytes, max_members)
    with _clean_on_error(dest):
        try:
            if kind == ".zip":
                _unzip(archive, dest, budget)
            else:
                _untar(archive, dest, budget)
        except InputError:
            raise
        except (zipfile.BadZipFile, zipfile.LargeZipFile, tarfile.TarError, EOFError, zlib.error, OSError,
                NotImplementedError, ValueError) as err:  # fmt: skip
            msg = f"not a readable {kind} archive: {' '.join(str(err).split())[:200] or type(err).__name__}"
            raise InputError(msg) from err

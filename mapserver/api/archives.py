"""Safe unpacking of ROS 2 bag directories uploaded as ``.zip`` or ``.tar`` archives.

Only regular files and directories are unpacked. An entry with an absolute path, a drive letter, a
backslash or a ``..`` component, a symbolic or hard link, a device, FIFO, sparse or any other special
file refuses the whole archive (nothing is kept), and so do encrypted zip entries.

Limits (:class:`ArchiveLimits`, each refusal a :class:`~mapserver.errors.LimitError` naming it):

* ``max_unpacked_bytes`` and ``max_unpacked_ratio``: the unpacked bytes may be at most
  ``min(max_unpacked_bytes, max_unpacked_ratio × the archive's own size)``. They are counted as the
  decompressor produces them, never trusted from the archive's headers: for a tar, every byte of the
  decompressed stream (headers and padding included) is counted, and an entry whose header declares more
  than the budget left is refused before its data is read; for a zip, every byte of member data (the
  declared sizes are checked first as well, and the zip reader never returns more than an entry declares).
* ``max_archive_entries``: entries (files and directories). A zip's count is read from its end record
  before the central directory is parsed, and a central directory larger than 4 KiB per allowed entry is
  refused unread; a tar's entries are counted as they come.

A tar's extended headers (pax, GNU long names) are held in memory by the tar reader: one larger than
:data:`MAX_TAR_HEADER_BYTES` refuses the archive before it is read.
"""

from __future__ import annotations

import bz2
import gzip
import io
import lzma
import shutil
import stat
import tarfile
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import IO, Any

from mapserver.errors import InputError, LimitError

ARCHIVE_SUFFIXES: tuple[str, ...] = (".zip", ".tar", ".tar.gz", ".tgz", ".tar.bz2", ".tar.xz")
MAX_TAR_HEADER_BYTES = 1 << 20
ZIP_CENTRAL_BYTES_PER_ENTRY = 4096
_COPY_CHUNK = 1 << 20
_EXTENDED_HEADERS = (tarfile.GNUTYPE_LONGNAME, tarfile.GNUTYPE_LONGLINK, tarfile.XHDTYPE, tarfile.XGLTYPE,
                     tarfile.SOLARIS_XHDTYPE)  # fmt: skip


@dataclass(frozen=True, slots=True)
class ArchiveLimits:
    """What one archive upload may unpack to (see the module docstring).

    Attributes:
        max_bytes: unpacked bytes at most (``max_unpacked_bytes``).
        max_ratio: unpacked bytes at most this multiple of the archive's own size (``max_unpacked_ratio``).
        max_entries: entries at most (``max_archive_entries``).
    """

    max_bytes: int
    max_ratio: float
    max_entries: int

    def budget(self, archive_bytes: int) -> tuple[int, str, str]:
        """Return the byte budget for an archive of ``archive_bytes``, the limit that sets it and its wording."""
        by_ratio = int(self.max_ratio * max(archive_bytes, 0))
        if by_ratio < self.max_bytes:
            why = f"max_unpacked_ratio = {self.max_ratio:g} × the archive's {archive_bytes} bytes"
            return by_ratio, "max_unpacked_ratio", why
        return self.max_bytes, "max_unpacked_bytes", f"max_unpacked_bytes = {self.max_bytes}"


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
    """Counts entries and unpacked bytes against the limits; raises :class:`LimitError` past either."""

    def __init__(self, limits: ArchiveLimits, archive_bytes: int) -> None:
        self.max_entries = limits.max_entries
        self.max_bytes, self.limit, self.why = limits.budget(archive_bytes)
        self.bytes = 0
        self.entries = 0

    def entry(self) -> None:
        self.entries += 1
        if self.entries > self.max_entries:
            self.too_many(f"more than {self.max_entries}")

    def too_many(self, count: str) -> None:
        msg = f"archive has {count} entries; the limit is max_archive_entries = {self.max_entries}"
        raise LimitError(msg, limit="max_archive_entries")

    def consume(self, count: int) -> None:
        self.bytes += count
        if self.bytes > self.max_bytes:
            self.too_big("unpacks to more than")

    def too_big(self, what: str, size: int | None = None) -> None:
        msg = f"archive {what} {self.max_bytes if size is None else size} bytes; the limit is {self.why}"
        raise LimitError(msg, limit=self.limit)


class _Counted(io.RawIOBase):
    """A readable stream that charges every byte it returns to a :class:`_Budget`."""

    def __init__(self, source: IO[bytes] | io.BufferedIOBase, budget: _Budget) -> None:
        super().__init__()
        self._source = source
        self._budget = budget

    def readable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        view = memoryview(buffer).cast("B")
        data = self._source.read(min(len(view), _COPY_CHUNK))
        self._budget.consume(len(data))
        view[: len(data)] = data
        return len(data)


def _copy(source: IO[bytes], target: Path, budget: _Budget | None) -> None:
    """Copy an entry's data to the new file ``target`` (charged to ``budget`` unless the stream is)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    try:
        handle = target.open("xb")
    except FileExistsError as err:
        msg = f"archive holds {target.name!r} twice"
        raise InputError(msg) from err
    with handle:
        while chunk := source.read(_COPY_CHUNK):
            if budget is not None:
                budget.consume(len(chunk))
            handle.write(chunk)


def _zip_end_record(archive: Path) -> tuple[int, int] | None:
    """Return (entries, central directory bytes) from a zip's end record (zip64 too), None without one."""
    with archive.open("rb") as handle:
        size = handle.seek(0, io.SEEK_END)
        tail_start = max(0, size - (22 + 65535))
        handle.seek(tail_start)
        tail = handle.read()
        at = tail.rfind(b"PK\x05\x06")
        if at < 0 or at + 22 > len(tail):
            return None
        entries = int.from_bytes(tail[at + 10 : at + 12], "little")
        central = int.from_bytes(tail[at + 12 : at + 16], "little")
        locator = at - 20
        zip64 = locator >= 0 and tail[locator : locator + 4] == b"PK\x06\x07"
        if zip64 and (entries == 0xFFFF or central == 0xFFFFFFFF):
            handle.seek(int.from_bytes(tail[locator + 8 : locator + 16], "little"))
            record = handle.read(56)
            if record[:4] == b"PK\x06\x06" and len(record) == 56:
                entries = int.from_bytes(record[32:40], "little")
                central = int.from_bytes(record[40:48], "little")
    return entries, central


def _unzip(archive: Path, dest: Path, budget: _Budget) -> None:
    end = _zip_end_record(archive)
    if end is not None:
        if end[0] > budget.max_entries:
            budget.too_many(str(end[0]))
        if end[1] > budget.max_entries * ZIP_CENTRAL_BYTES_PER_ENTRY:
            budget.too_many(f"a {end[1]}-byte directory of more than {budget.max_entries}")
    with zipfile.ZipFile(archive) as zf:
        infos = zf.infolist()
        if len(infos) > budget.max_entries:
            budget.too_many(str(len(infos)))
        declared = sum(i.file_size for i in infos)
        if declared > budget.max_bytes:
            budget.too_big("declares", declared)
        for info in infos:
            budget.entry()
            _unzip_entry(zf, info, _member_path(info.filename, dest), budget)


def _unzip_entry(zf: zipfile.ZipFile, info: zipfile.ZipInfo, target: Path, budget: _Budget) -> None:
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
        return
    with zf.open(info) as source:
        _copy(source, target, budget)


class _BoundedTarInfo(tarfile.TarInfo):
    """A tar header that refuses extended headers (pax, GNU long names) over :data:`MAX_TAR_HEADER_BYTES`."""

    def _proc_member(self, tarfile: Any) -> Any:
        if self.type in _EXTENDED_HEADERS and self.size > MAX_TAR_HEADER_BYTES:
            msg = f"archive has an extended tar header of {self.size} bytes (at most {MAX_TAR_HEADER_BYTES} accepted)"
            raise InputError(msg)
        return super()._proc_member(tarfile)  # type: ignore[misc]  # typeshed omits TarInfo's private hooks


def _decompressed(archive: Path) -> IO[bytes] | io.BufferedIOBase:
    """Open ``archive`` as its decompressed byte stream (gzip, bzip2, xz or plain, told by its magic bytes)."""
    with archive.open("rb") as handle:
        magic = handle.read(6)
    if magic[:2] == b"\x1f\x8b":
        return gzip.open(archive, "rb")
    if magic[:3] == b"BZh":
        return bz2.open(archive, "rb")
    if magic == b"\xfd7zXZ\x00":
        return lzma.open(archive, "rb")
    return archive.open("rb")


def _untar(archive: Path, dest: Path, budget: _Budget) -> None:
    with _decompressed(archive) as raw, _Counted(raw, budget) as counted, tarfile.open(
        fileobj=counted, mode="r|", tarinfo=_BoundedTarInfo
    ) as tf:  # fmt: skip
        for member in tf:
            budget.entry()
            target = _member_path(member.name, dest)
            if member.isdir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            if not member.isreg() or member.issparse():
                kind = "a link" if (member.issym() or member.islnk()) else "a special file"
                msg = f"archive entry {member.name!r} is {kind}; only files and directories are accepted"
                raise InputError(msg)
            if member.offset_data + member.size > budget.max_bytes:  # refused before its data is read
                budget.too_big(f"entry {member.name!r} of {member.size} bytes ends past", budget.max_bytes)
            source = tf.extractfile(member)
            if source is None:  # pragma: no cover - isreg() members always have data
                msg = f"archive entry {member.name!r} has no data"
                raise InputError(msg)
            with source:
                _copy(source, target, None)  # the decompressed stream is charged already


@contextmanager
def _clean_on_error(dest: Path) -> Iterator[None]:
    try:
        yield
    except BaseException:
        shutil.rmtree(dest, ignore_errors=True)
        raise


def extract_archive(archive: Path, dest: Path, *, kind: str, limits: ArchiveLimits) -> None:
    """Unpack ``archive`` (``kind`` from :func:`archive_suffix`) into the new directory ``dest``.

    Raises:
        LimitError: the archive passes one of ``limits`` (nothing is kept).
        InputError: unreadable archive or an unsafe entry (see the module docstring); ``dest`` is removed.
    """
    dest.mkdir(parents=True, exist_ok=False)
    budget = _Budget(limits, archive.stat().st_size)
    with _clean_on_error(dest):
        try:
            if kind == ".zip":
                _unzip(archive, dest, budget)
            else:
                _untar(archive, dest, budget)
        except InputError:
            raise
        except (zipfile.BadZipFile, zipfile.LargeZipFile, tarfile.TarError, EOFError, zlib.error, lzma.LZMAError,
                OSError, NotImplementedError, ValueError) as err:  # fmt: skip
            msg = f"not a readable {kind} archive ({_reason(err)})"
            raise InputError(msg) from err


def _reason(err: BaseException) -> str:
    """Return a short reason for an archive read error, without paths or exception names."""
    if isinstance(err, EOFError | tarfile.ReadError) and "empty" not in str(err):
        return "it ends early or is damaged"
    if isinstance(err, OSError) and err.filename is not None:
        return "it cannot be read"
    text = " ".join(str(err).split())
    return text[:120] if text and "/" not in text else "damaged data"

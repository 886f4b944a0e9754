"""Receiving uploads: a streaming ``multipart/form-data`` parser that writes the file part to disk.

The request body is never held whole in memory: chunks are parsed as they arrive, the file part is
written to a staging file in the upload directory and hashed (SHA-256) on the way, and the upload is
refused with 413 as soon as it passes the size limit (before reading further when ``Content-Length``
already says so); a refused or broken upload leaves no file behind. Reading stops at the multipart
closing boundary: a body that goes on past it by more than ``max_trailing_bytes`` is refused (400) without
reading the rest, and an upload that sends nothing for ``read_timeout_s`` is answered 408.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import re
import secrets
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import anyio
from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect, Request

from mapserver.api.errors import PayloadTooLargeError, RequestTimeoutError, UnsupportedMediaError
from mapserver.errors import InputError

logger = logging.getLogger(__name__)

FILE_FIELD = "file"
MAX_FIELD_BYTES = 64 * 1024
MAX_FIELDS = 16
MULTIPART_OVERHEAD = 1 << 20
"""Bytes of the request body allowed beyond the file itself (boundaries, headers, small fields)."""

_SAFE = re.compile(r"[^A-Za-z0-9._-]+")


def safe_filename(name: str | None, default: str = "upload") -> str:
    """Return a file name without directories or unusual characters (``../x y.bag`` → ``x_y.bag``)."""
    base = (name or "").replace("\\", "/").rsplit("/", 1)[-1]
    cleaned = _SAFE.sub("_", base).lstrip(".-")[:120]
    return cleaned or default


@dataclass
class ReceivedUpload:
    """An upload written to the staging directory, with the form's text fields.

    Attributes:
        path: the staged file (delete it, or move it, when done).
        filename: the client's file name, made safe (:func:`safe_filename`).
        size: bytes received.
        sha256: hex SHA-256 of the bytes.
        fields: the text fields (``preset``, ``map``, ``topics``, ...).
    """

    path: Path
    filename: str
    size: int
    sha256: str
    fields: dict[str, str] = field(default_factory=dict)

    def discard(self) -> None:
        """Delete the staged file (idempotent)."""
        self.path.unlink(missing_ok=True)


class _FormSink:
    """python-multipart callbacks: text fields to memory (bounded), the file part to disk (bounded)."""

    def __init__(self, target: Path, max_bytes: int) -> None:
        self.target = target
        self.max_bytes = max_bytes
        self.fields: dict[str, str] = {}
        self.filename: str | None = None
        self.size = 0
        self.digest = hashlib.sha256()
        self.handle: IO[bytes] | None = None
        self._header_name = b""
        self._header_value = b""
        self._disposition = b""
        self._name: str | None = None
        self._is_file = False
        self._buffer = bytearray()
        self._files = 0
        self.ended = False

    def callbacks(self) -> dict[str, object]:
        return {
            "on_part_begin": self.on_part_begin,
            "on_part_data": self.on_part_data,
            "on_part_end": self.on_part_end,
            "on_header_field": self.on_header_field,
            "on_header_value": self.on_header_value,
            "on_header_end": self.on_header_end,
            "on_headers_finished": self.on_headers_finished,
            "on_end": self.on_end,
        }

    def on_part_begin(self) -> None:
        self._disposition = b""
        self._name = None
        self._is_file = False
        self._buffer = bytearray()

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._header_name += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._header_value += data[start:end]

    def on_header_end(self) -> None:
        if self._header_name.strip().lower() == b"content-disposition":
            self._disposition = self._header_value
        self._header_name = b""
        self._header_value = b""

    def on_headers_finished(self) -> None:
        _, options = parse_options_header(self._disposition)
        raw_name = options.get(b"name")
        if raw_name is None:
            msg = "a multipart part has no Content-Disposition name"
            raise InputError(msg)
        self._name = raw_name.decode("utf-8", "replace")
        if self._name == FILE_FIELD:
            self._files += 1
            if self._files > 1:
                msg = f"send exactly one {FILE_FIELD!r} part"
                raise InputError(msg)
            self._is_file = True
            self.filename = options.get(b"filename", b"").decode("utf-8", "replace")
            self.handle = self.target.open("xb")
        elif len(self.fields) >= MAX_FIELDS:
            msg = f"too many form fields (at most {MAX_FIELDS})"
            raise InputError(msg)

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        chunk = data[start:end]
        if self._is_file:
            self.size += len(chunk)
            if self.size > self.max_bytes:
                msg = f"upload larger than the server's limit of {self.max_bytes} bytes (max_upload_bytes)"
                raise PayloadTooLargeError(msg)
            self.digest.update(chunk)
            assert self.handle is not None
            self.handle.write(chunk)
            return
        if len(self._buffer) + len(chunk) > MAX_FIELD_BYTES:
            msg = f"form field {self._name!r} is longer than {MAX_FIELD_BYTES} bytes"
            raise InputError(msg)
        self._buffer.extend(chunk)

    def on_part_end(self) -> None:
        if self._is_file:
            assert self.handle is not None
            self.handle.close()
        elif self._name is not None:
            if self._name in self.fields:
                msg = f"form field {self._name!r} given twice"
                raise InputError(msg)
            self.fields[self._name] = self._buffer.decode("utf-8", "replace")

    def on_end(self) -> None:
        self.ended = True

    def close(self) -> None:
        if self.handle is not None and not self.handle.closed:
            with contextlib.suppress(OSError):  # a full disk fails the last flush too; the file is removed anyway
                self.handle.close()


def _boundary(request: Request) -> bytes:
    content_type = request.headers.get("content-type", "")
    kind, options = parse_options_header(content_type)
    if kind != b"multipart/form-data":
        msg = f"send the log as multipart/form-data with a {FILE_FIELD!r} part (got {content_type or 'no'!r} body)"
        raise UnsupportedMediaError(msg)
    boundary = options.get(b"boundary")
    if not boundary:
        msg = "multipart/form-data body without a boundary"
        raise InputError(msg)
    return boundary


async def _chunks(request: Request, read_timeout_s: float) -> AsyncIterator[bytes]:
    """Yield the request body's chunks; 408 when the client sends nothing for ``read_timeout_s`` seconds."""
    stream = request.stream()
    while True:
        with anyio.move_on_after(read_timeout_s) as waited:
            chunk = await anext(stream, None)
        if waited.cancelled_caught:
            msg = f"the upload sent nothing for {read_timeout_s:g} s; send the whole body without pausing that long"
            raise RequestTimeoutError(msg)
        if chunk is None:
            return
        yield chunk


async def _parse(
    request: Request, parser: MultipartParser, sink: _FormSink, read_timeout_s: float, max_trailing: int
) -> None:
    """Feed the body to the parser up to its closing boundary; refuse more than ``max_trailing`` bytes after it."""
    trailing = 0
    async for chunk in _chunks(request, read_timeout_s):
        if sink.ended:
            trailing += len(chunk)
            if trailing > max_trailing:
                msg = (f"the body goes on after the multipart closing boundary for more than {max_trailing} "
                       "bytes (max_trailing_bytes); send nothing after it")
                raise InputError(msg)
        elif chunk:
            await run_in_threadpool(parser.write, chunk)


async def receive_upload(
    request: Request, *, staging: Path, max_bytes: int, read_timeout_s: float = 60.0, max_trailing_bytes: int = 1024
) -> ReceivedUpload:
    """Stream a multipart upload's ``file`` part to ``staging`` (hashing it) and collect its text fields.

    Args:
        request: the incoming request (its body is consumed up to the closing boundary).
        staging: directory for the staged file (created).
        max_bytes: largest accepted file part.
        read_timeout_s: longest wait for the body's next bytes.
        max_trailing_bytes: most bytes after the closing boundary (an epilogue, RFC 2046).

    Returns:
        The staged upload.

    Raises:
        UnsupportedMediaError: not multipart/form-data (415).
        PayloadTooLargeError: the body or the file part is over the limit (413).
        InputError: malformed multipart body, no ``file`` part, an empty file, or more than a short epilogue
            after the closing boundary (400).
        RequestTimeoutError: the client sent nothing for ``read_timeout_s`` (408).
    """
    boundary = _boundary(request)
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > max_bytes + MULTIPART_OVERHEAD:
        msg = (
            f"upload of {int(declared)} bytes is larger than the server's limit of {max_bytes} bytes "
            "(max_upload_bytes)"
        )
        raise PayloadTooLargeError(msg)
    staging.mkdir(parents=True, exist_ok=True)
    target = staging / f"{secrets.token_hex(12)}.part"
    sink = _FormSink(target, max_bytes)
    parser = MultipartParser(boundary, sink.callbacks())  # type: ignore[arg-type]
    try:
        await _parse(request, parser, sink, read_timeout_s, max_trailing_bytes)
        parser.finalize()
        if sink.filename is None:
            msg = f"the upload has no {FILE_FIELD!r} part"
            raise InputError(msg)
        if sink.size == 0:
            msg = "the uploaded file is empty"
            raise InputError(msg)
        if sink.handle is None or not sink.handle.closed:
            msg = "the multipart body ended inside the file part (truncated upload)"
            raise InputError(msg)
    except FormParserError as err:
        sink.close()
        target.unlink(missing_ok=True)
        msg = f"malformed multipart body: {' '.join(str(err).split())[:200]}"
        raise InputError(msg) from err
    except ClientDisconnect as err:
        sink.close()
        target.unlink(missing_ok=True)
        msg = "the client disconnected during the upload"
        raise InputError(msg) from err
    except BaseException:
        sink.close()
        target.unlink(missing_ok=True)
        raise
    return ReceivedUpload(
        path=target,
        filename=safe_filename(sink.filename),
        size=sink.size,
        sha256=sink.digest.hexdigest(),
        fields=sink.fields,
    )

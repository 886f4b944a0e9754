"""Hostile inputs for the tests (and ``bench/hostile_input.py``): archive and image bombs, bad odometry, damaged logs.

Everything is generated in tmp_path; nothing binary is committed. Also the checks the tests share: the
non-finite floats in a database, and a process's I/O and memory figures from ``/proc``.
"""

from __future__ import annotations

import bz2
import gzip
import io
import math
import random
import tarfile
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any
from unittest import mock

import cv2
import numpy as np
import sqlalchemy as sa

from mapserver.ingest import writer
from mapserver.ingest.writer import OdomSample, write_log
from tests.mapserver.api.logs import T0_NS, write_strip_log

CHUNK = 16 << 20


# ------------------------------------------------------------------------------------------- archive bombs
def _tar_prefix(size: int) -> bytes:
    """Return a tar's bytes up to the data of its ``bag/zeros.db3`` member (``bag/metadata.yaml`` first)."""
    buffer = io.BytesIO()
    meta = b"rosbag2_bagfile_information: {}\n"
    info = tarfile.TarInfo("bag/metadata.yaml")
    info.size = len(meta)
    buffer.write(info.tobuf(tarfile.PAX_FORMAT))
    buffer.write(meta + bytes(-len(meta) % 512))
    zeros = tarfile.TarInfo("bag/zeros.db3")
    zeros.size = size
    buffer.write(zeros.tobuf(tarfile.PAX_FORMAT))
    return buffer.getvalue()


def zeros_tar(path: Path, size: int, codec: str, *, one_stream: bool = False) -> Path:
    """Write a bag directory holding ``size`` zero bytes as a tar compressed with ``bz2`` or ``gz``.

    By default the file is several concatenated streams (both readers read them as one): one for the tar
    headers, then one stream of ``CHUNK`` zeros repeated, so even gigabytes take a moment to build.
    ``one_stream`` compresses it all as one stream, as a bomb found in the wild would be (2 GiB: a 1.6 KB
    bzip2 file in ~30 s, a 2 MB gzip file in ~15 s).
    """
    total = size + (-size % 512) + 1024 + 10240  # data, its padding, the end blocks and the record's padding
    with path.open("wb") as out:
        if one_stream:
            compressor: Any = bz2.BZ2Compressor(9) if codec == "bz2" else zlib.compressobj(9, wbits=31)
            out.write(compressor.compress(_tar_prefix(size)))
            zeros = bytes(CHUNK)
            for _ in range(total // CHUNK):
                out.write(compressor.compress(zeros))
            out.write(compressor.compress(bytes(total % CHUNK)) + compressor.flush())
            return path
        compress: Callable[[bytes], bytes] = (lambda b: bz2.compress(b, 9)) if codec == "bz2" else (
            lambda b: gzip.compress(b, 9))  # fmt: skip
        block = compress(bytes(CHUNK))
        out.write(compress(_tar_prefix(size)))
        for _ in range(total // CHUNK):
            out.write(block)
        out.write(compress(bytes(total % CHUNK)))
    return path


def zeros_zip(path: Path, size: int) -> Path:
    """Write a bag directory holding ``size`` zero bytes, deflated, as a zip (zip64, honest headers)."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("bag/metadata.yaml", b"rosbag2_bagfile_information: {}\n")
        with zf.open("bag/zeros.db3", "w", force_zip64=True) as handle:
            for start in range(0, size, CHUNK):
                handle.write(bytes(min(CHUNK, size - start)))
    return path


def entries_zip(path: Path, count: int) -> Path:
    """Write a zip of ``count`` empty entries."""
    with zipfile.ZipFile(path, "w") as zf:
        for k in range(count):
            zf.writestr(f"bag/f{k:06d}", b"")
    return path


# --------------------------------------------------------------------------------------------- image bombs
def png_bomb(width: int, height: int) -> bytes:
    """Return a valid grey PNG of zeros of that size (one zlib stream of the filtered rows: ~1 KB per Mpx)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return len(data).to_bytes(4, "big") + kind + data + zlib.crc32(kind + data).to_bytes(4, "big")

    compressor = zlib.compressobj(9)
    rows = bytes(width + 1) * max(1, CHUNK // (width + 1))
    per = len(rows) // (width + 1)
    parts = [compressor.compress(rows) for _ in range(height // per)]
    parts.append(compressor.compress(bytes(width + 1) * (height % per)))
    idat = b"".join(parts) + compressor.flush()
    ihdr = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([8, 0, 0, 0, 0])
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def jpeg_bomb(width: int, height: int, *, progressive: bool = False) -> bytes:
    """Return a small JPEG whose frame header (SOF) says ``width`` × ``height``.

    libjpeg allocates the whole frame from the header and pads missing data, so decoding it costs
    width × height bytes (grey) however small the file is.
    """
    params = [cv2.IMWRITE_JPEG_QUALITY, 50, cv2.IMWRITE_JPEG_PROGRESSIVE, int(progressive)]
    ok, data = cv2.imencode(".jpg", np.full((16, 16), 128, np.uint8), params)
    assert ok
    raw = bytearray(data.tobytes())
    marker = 0xC2 if progressive else 0xC0
    at = raw.find(bytes([0xFF, marker]))
    assert at > 0
    raw[at + 5 : at + 7] = height.to_bytes(2, "big")
    raw[at + 7 : at + 9] = width.to_bytes(2, "big")
    return bytes(raw)


def payload_bag(path: Path, payloads: list[bytes], fmt: str, *, rate_hz: float = 2.0) -> Path:
    """Write a ROS 1 bag of compressed frames with these payloads (``png`` or ``jpeg``) and odometry."""
    images = [(T0_NS + round(k * 1e9 / rate_hz), np.zeros((2, 2), np.uint8)) for k in range(len(payloads))]
    count = int(len(payloads) / rate_hz * 10) + 2
    odometry = [OdomSample(T0_NS + k * 100_000_000, 0.1 * k, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0) for k in range(count)]
    stream = iter([np.frombuffer(p, np.uint8) for p in payloads])
    with mock.patch.object(writer, "encode_compressed", lambda pixels, kind, *quality: next(stream)):
        return write_log(path, "bag", images, odometry, image_encoding=fmt)  # type: ignore[arg-type]


def encoded(fmt: str, width: int, height: int, seed: int = 0) -> bytes:
    """Return an ordinary ``fmt`` image of that size (textured, seeded)."""
    pixels = (np.random.default_rng(seed).random((height, width)) * 255).astype(np.uint8)
    ok, data = cv2.imencode(".png" if fmt == "png" else ".jpg", pixels)
    assert ok
    return data.tobytes()


# ------------------------------------------------------------------------------------------- bad odometry
def bad_odometry_log(path: Path, values: dict[str, float], indexes: list[int] | None, *, fmt: str = "bag",
                     pose_only: bool = False) -> Path:  # fmt: skip
    """Write the API tests' strip log with the ``OdomSample`` fields in ``values`` set on some samples.

    ``indexes``: the samples changed (None: every one).
    """

    def edit(samples: list[OdomSample]) -> list[OdomSample]:
        chosen = range(len(samples)) if indexes is None else indexes
        out = list(samples)
        for k in chosen:
            out[k] = replace(out[k], **values)
        return out

    return write_strip_log(path, fmt=fmt, odometry_edit=edit, pose_only=pose_only)


def nonfinite_floats(db_url: str) -> dict[str, int]:
    """Return ``{"table.column": rows}`` of every float column holding a non-finite value (SQLite, PostgreSQL).

    SQLite stores NaN as NULL, so a NULL in a NOT NULL float column counts too (that cannot happen: it is how
    a NaN would show); ±inf is a value beyond the largest double.
    """
    engine = sa.create_engine(db_url)
    found: dict[str, int] = {}
    try:
        inspector = sa.inspect(engine)
        with engine.connect() as conn:
            for table in inspector.get_table_names():
                for column in inspector.get_columns(table):
                    if not isinstance(column["type"], sa.Float):
                        continue
                    name = f'"{column["name"]}"'
                    bad = f"{name} != {name} OR {name} > 1.7976931348623157e308 OR {name} < -1.7976931348623157e308"
                    if not column["nullable"]:
                        bad += f" OR {name} IS NULL"
                    rows = conn.execute(sa.text(f'SELECT COUNT(*) FROM "{table}" WHERE ({bad})')).scalar_one()
                    if rows:
                        found[f"{table}.{column['name']}"] = int(rows)
    finally:
        engine.dispose()
    return found


def float_columns(db_url: str) -> list[str]:
    """Return ``table.column`` of every float column (what :func:`nonfinite_floats` checks)."""
    engine = sa.create_engine(db_url)
    try:
        inspector = sa.inspect(engine)
        return [f"{t}.{c['name']}" for t in inspector.get_table_names() for c in inspector.get_columns(t)
                if isinstance(c["type"], sa.Float)]  # fmt: skip
    finally:
        engine.dispose()


# ------------------------------------------------------------------------------------------- damaged logs
def damaged(data: bytes, seed: int) -> tuple[str, bytes]:
    """Return a damaged copy of a log's bytes: truncated, a bit flipped, or a run zeroed or randomised."""
    rng = random.Random(seed)
    kind = ("truncated", "bit", "zeros", "random")[seed % 4]
    if kind == "truncated":
        return kind, data[: rng.randrange(len(data) // 20, len(data) - 1)]
    out = bytearray(data)
    at = rng.randrange(len(out) - 8)
    if kind == "bit":
        out[at] ^= 1 << rng.randrange(8)
    elif kind == "zeros":
        out[at : at + 8] = bytes(8)
    else:
        out[at : at + 4] = rng.randbytes(4)
    return kind, bytes(out)


# ------------------------------------------------------------------------------------------- measurements
def proc_figures(pid: int) -> dict[str, int]:
    """Return a process's ``/proc`` I/O counters (``wchar``, ``write_bytes``, ...) and ``VmHWM``/``VmRSS`` bytes."""
    values: dict[str, int] = {}
    for line in Path(f"/proc/{pid}/io").read_text().splitlines():
        key, value = line.split(":")
        values[key] = int(value)
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(("VmHWM", "VmRSS")):
            values[line.split(":")[0]] = int(line.split()[1]) * 1024
    return values


def finite(value: Any) -> bool:
    """Return True for a finite number (False for NaN, ±inf and non-numbers)."""
    return isinstance(value, int | float) and math.isfinite(value)

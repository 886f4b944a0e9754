"""numpy arrays ↔ database blobs, exactly (dtype, shape and every bit).

* :func:`pack_npz` / :func:`unpack_npz`: a dict of arrays as a zlib-compressed ``.npz`` (no pickles; level
  :data:`ZLIB_LEVEL`, arrays that do not shrink stored as they are: an ``sdr-htm`` snapshot took 1.5 s to
  compress at numpy's level 6).
* :func:`pack_raw` / :func:`unpack_raw`: one array's raw little-endian bytes, zlib-compressed; the
  dtype and shape travel separately (the state manifest).
* :func:`negative_zeros`: where an array holds ``-0.0``. SQLite stores a REAL that has an integral
  value as an integer, which drops the sign of zero; the state writer records these positions and the
  reader puts the sign back, so a round trip is bit-exact on every backend.
"""

from __future__ import annotations

import io
import zipfile
import zlib
from collections.abc import Mapping, Sequence

import numpy as np
import numpy.typing as npt

from mapserver.errors import StoreError

ZLIB_LEVEL = 1
"""zlib level for raw arrays and npz archives: level 1 is several times faster than 6 and pose-cell activity is
mostly zeros."""


COMPRESS_SAMPLE = 65536
"""Bytes of an array tried before deflating it whole (:func:`_compresses`)."""


def _little_endian(array: np.ndarray) -> np.ndarray:
    dtype = array.dtype
    if dtype.byteorder == ">" or (dtype.byteorder == "=" and not np.little_endian):
        return array.astype(dtype.newbyteorder("<"))
    return array


def pack_npz(arrays: Mapping[str, npt.ArrayLike]) -> bytes:
    """Return ``arrays`` as the bytes of a compressed ``.npz`` archive.

    Raises:
        StoreError: an array has an object dtype (it cannot be stored without pickling).
    """
    plain = {}
    for key, value in arrays.items():
        array = np.asarray(value)
        if array.dtype.hasobject:
            msg = f"snapshot array {key!r} has dtype object and cannot be stored"
            raise StoreError(msg)
        plain[key] = array
    buffer = io.BytesIO()  # np.savez_compressed's layout (one ``KEY.npy`` per array), at ZLIB_LEVEL, not 6
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED, compresslevel=ZLIB_LEVEL) as archive:
        for key, array in plain.items():
            member = zipfile.ZipInfo(f"{key}.npy")  # a fixed date: the same arrays give the same bytes
            member.compress_type = zipfile.ZIP_DEFLATED if _compresses(array) else zipfile.ZIP_STORED
            with archive.open(member, "w", force_zip64=True) as out:
                np.lib.format.write_array(out, array, allow_pickle=False)
    return buffer.getvalue()


def _compresses(array: np.ndarray) -> bool:
    """Whether deflating ``array`` pays: its first 64 KiB shrink below 80 %.

    Random floats do not: an ``sdr-htm`` snapshot's LSBH projection (6.3 MB) deflates to 93 % in 0.2 s and its
    pooler's permanences (4.9 MB) to 88 % in 0.16 s, and a merge archives three snapshots. Lattices, links
    and packed codes do (to 1–20 %).
    """
    head = np.ascontiguousarray(array).reshape(-1)[: COMPRESS_SAMPLE // max(array.itemsize, 1)].tobytes()
    return len(head) < 1024 or len(zlib.compress(head, ZLIB_LEVEL)) < 0.8 * len(head)


def unpack_npz(blob: bytes) -> dict[str, np.ndarray]:
    """Return the arrays of a blob written by :func:`pack_npz`.

    Raises:
        StoreError: the blob is not a readable npz archive.
    """
    try:
        with np.load(io.BytesIO(blob), allow_pickle=False) as archive:
            return {key: archive[key] for key in archive.files}
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        msg = f"stored arrays are corrupt: {err}"
        raise StoreError(msg) from err


def pack_raw(array: npt.ArrayLike) -> bytes:
    """Return the array's C-order little-endian bytes, zlib-compressed."""
    data = _little_endian(np.ascontiguousarray(array))
    return zlib.compress(data.tobytes(), ZLIB_LEVEL)


def unpack_raw(blob: bytes, dtype: npt.DTypeLike, shape: Sequence[int]) -> np.ndarray:
    """Return the array stored by :func:`pack_raw` with the given dtype (any byte order) and shape.

    Raises:
        StoreError: the blob is corrupt or its size does not match ``dtype`` × ``shape``.
    """
    target = np.dtype(dtype)
    try:
        raw = zlib.decompress(blob)
        values = np.frombuffer(raw, dtype=target.newbyteorder("<")).reshape(tuple(shape))
    except (zlib.error, ValueError) as err:
        msg = f"stored array of dtype {target.str} and shape {tuple(shape)!r} is corrupt: {err}"
        raise StoreError(msg) from err
    return values.astype(target, copy=True)


def negative_zeros(array: npt.ArrayLike) -> np.ndarray:
    """Return the flat indices (int64) of the ``-0.0`` elements of a floating-point array (empty otherwise)."""
    values = np.asarray(array)
    if not np.issubdtype(values.dtype, np.floating) or values.size == 0:
        return np.zeros(0, dtype=np.int64)
    flat = values.reshape(-1)
    return np.flatnonzero((flat == 0) & np.signbit(flat)).astype(np.int64)


def restore_negative_zeros(array: np.ndarray, indices: npt.ArrayLike) -> None:
    """Set the elements at flat ``indices`` of ``array`` (in place) to ``-0.0``."""
    idx = np.asarray(indices, dtype=np.int64)
    if idx.size:
        array.reshape(-1)[idx] = -0.0

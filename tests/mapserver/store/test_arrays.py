"""numpy arrays ↔ blobs: the npz archive numpy itself reads, exact, at the store's zlib level."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from mapserver.errors import StoreError
from mapserver.store.arrays import pack_npz, unpack_npz


def test_an_npz_blob_is_an_archive_numpy_reads_back_exactly() -> None:
    arrays = {
        "pose": np.array([[0.5, -0.0, 1e-300], [np.inf, -np.inf, 3.0]]),
        "ids": np.arange(7, dtype=np.int64)[::-1],
        "big_endian": np.array([1.5, 2.5], dtype=">f4"),
        "empty": np.zeros((0, 4), dtype=np.float32),
        "scalar": np.asarray(-3, dtype=np.int8),
        "bits": np.zeros((300, 256), dtype=np.uint8),
    }
    blob = pack_npz(arrays)
    with np.load(io.BytesIO(blob), allow_pickle=False) as archive:  # numpy's own reader, no helper of ours
        assert sorted(archive.files) == sorted(arrays)
        for key, array in arrays.items():
            got = archive[key]
            assert got.dtype == array.dtype and got.shape == array.shape
            assert got.tobytes() == array.tobytes()  # every bit, -0.0 included
    back = unpack_npz(blob)
    assert np.signbit(back["pose"][0, 1])
    assert pack_npz(arrays) == blob  # the same arrays, the same bytes (no clock in the archive)


def test_arrays_that_deflate_are_deflated_and_random_floats_are_stored_as_they_are() -> None:
    rng = np.random.default_rng(3)
    arrays = {"bits": np.zeros((300, 256), dtype=np.uint8), "noise": rng.standard_normal((256, 128)).astype(np.float32),
              "tiny": np.array([1.0, 2.0])}  # fmt: skip
    blob = pack_npz(arrays)
    with zipfile.ZipFile(io.BytesIO(blob)) as archive:
        members = {m.filename: m for m in archive.infolist()}
    assert members["bits.npy"].compress_type == zipfile.ZIP_DEFLATED
    assert members["bits.npy"].compress_size < members["bits.npy"].file_size / 50  # 76,800 zero bytes
    assert members["noise.npy"].compress_type == zipfile.ZIP_STORED  # deflate saves ~7 % of random floats
    assert members["noise.npy"].compress_size == members["noise.npy"].file_size
    assert members["tiny.npy"].compress_type == zipfile.ZIP_DEFLATED  # under 1 KiB: not worth a trial
    back = unpack_npz(blob)
    assert all(back[k].tobytes() == arrays[k].tobytes() for k in arrays)


def test_an_object_array_is_refused_and_a_damaged_blob_is_a_store_error() -> None:
    with pytest.raises(StoreError, match="dtype object"):
        pack_npz({"x": np.array([object()])})
    blob = pack_npz({"x": np.arange(1000.0)})
    with pytest.raises(StoreError, match="corrupt"):
        unpack_npz(blob[: len(blob) // 2])

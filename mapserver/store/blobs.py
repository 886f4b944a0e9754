"""Content-addressed blobs: large arrays that many map states share, stored once per database.

An ``sdr-htm`` map's snapshot holds its LSBH projection (``nc_projection``: 6.3 MB of float32 at the default
sizes, incompressible), the same array for every map made with one seed and size. Every map state and every
archive of a merge used to hold a copy. :func:`share_arrays` moves each array named in :data:`SHARED_KEYS` into
the ``blobs`` table under the SHA-256 of its ``.npy`` bytes (dtype, shape and every bit) and leaves
``__blob__.KEY`` (the digest, as ASCII bytes) in its place; :func:`resolve_arrays` puts the array back, checking
the digest. A state written before migration 0006 still holds its copy and reads as before.

Blobs are never deleted: a projection is shared by every state of every map made with it, maps are dropped only
into an archive (a merge) and archives stay, so a blob that nothing refers to does not arise in normal use.
"""

from __future__ import annotations

import hashlib
import io
from collections.abc import Mapping

import numpy as np
from sqlalchemy import Connection, select
from sqlalchemy.dialects.postgresql import insert as postgresql_insert
from sqlalchemy.dialects.sqlite import insert as sqlite_insert

from mapserver.store.errors import CorruptStateError
from mapserver.store.models import Blob, utcnow

SHARED_KEYS: tuple[str, ...] = ("nc_projection",)
"""Snapshot arrays stored once per database (identical across maps made with the same parameters)."""

REF_PREFIX = "__blob__."
"""Key under which a state holds a shared array's digest instead of the array."""


def npy_bytes(array: np.ndarray) -> bytes:
    """Return ``array`` as the bytes of a ``.npy`` file (its dtype, shape and every bit; no pickles)."""
    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, np.asarray(array), allow_pickle=False)
    return buffer.getvalue()


def share_arrays(conn: Connection, arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Store the :data:`SHARED_KEYS` arrays of ``arrays`` as blobs (once) and return ``arrays`` referring to them."""
    out = dict(arrays)
    for key in SHARED_KEYS:
        if key not in out:
            continue
        data = npy_bytes(out.pop(key))
        digest = hashlib.sha256(data).hexdigest()
        _put(conn, digest, data)
        out[REF_PREFIX + key] = np.frombuffer(digest.encode("ascii"), dtype=np.uint8).copy()
    return out


def resolve_arrays(conn: Connection, arrays: Mapping[str, np.ndarray], what: str) -> dict[str, np.ndarray]:
    """Return ``arrays`` with every blob reference replaced by its array.

    Raises:
        CorruptStateError: a referenced blob is missing, or its bytes do not have the digest they are stored under.
    """
    out = dict(arrays)
    for ref in [k for k in out if k.startswith(REF_PREFIX)]:
        digest = np.asarray(out.pop(ref), dtype=np.uint8).tobytes().decode("ascii")
        data = conn.execute(select(Blob.data).where(Blob.digest == digest)).scalar_one_or_none()
        if data is None or hashlib.sha256(bytes(data)).hexdigest() != digest:
            state = "missing" if data is None else "damaged"
            msg = f"{what}: the shared array {ref[len(REF_PREFIX):]!r} (blob {digest[:12]}…) is {state}"
            raise CorruptStateError(msg)
        out[ref[len(REF_PREFIX) :]] = np.load(io.BytesIO(bytes(data)), allow_pickle=False)
    return out


def _put(conn: Connection, digest: str, data: bytes) -> None:
    """Insert a blob unless one with this digest exists (two writers may race: the second one's insert is a no-op)."""
    if conn.execute(select(Blob.digest).where(Blob.digest == digest)).first() is not None:
        return  # stored already: do not send its bytes again
    values = {"digest": digest, "nbytes": len(data), "data": data, "created_at": utcnow()}
    if conn.dialect.name == "postgresql":
        conn.execute(postgresql_insert(Blob).values(**values).on_conflict_do_nothing(index_elements=["digest"]))
    elif conn.dialect.name == "sqlite":
        conn.execute(sqlite_insert(Blob).values(**values).on_conflict_do_nothing(index_elements=["digest"]))
    else:
        conn.execute(Blob.__table__.insert().values(**values))

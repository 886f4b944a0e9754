"""The ``map_states`` row: the manifest, the npz of keys kept outside the row tables, the pose-cell activity.

:func:`write_state_row` stores them (with the ``-0.0`` patches of the row tables' float columns, which SQLite
drops); :func:`assemble_snapshot` rebuilds the snapshot the manifest describes from them and the rows read.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from sqlalchemy import Connection, insert

from mapserver.store.arrays import negative_zeros, pack_npz, pack_raw, restore_negative_zeros, unpack_raw
from mapserver.store.blobs import share_arrays
from mapserver.store.errors import CorruptStateError
from mapserver.store.health import map_health
from mapserver.store.models import MapState, utcnow
from mapserver.store.state_layout import ACTIVITY_KEY, NEGZERO_PREFIX, PLACES, ROW_FLOAT_KEYS
from mapserver.store.state_validate import Shapes


def _scalar(snapshot: Mapping[str, Any], key: str, default: float) -> float:
    """Return the one-value array ``snapshot[key]`` as a float; ``default`` when missing or not one value."""
    if key not in snapshot:
        return default
    value = np.asarray(snapshot[key])
    return float(value) if value.size == 1 else default


def write_state_row(
    conn: Connection, map_id: int, snapshot: Mapping[str, Any], shapes: Shapes, params: Any
) -> None:
    """Replace the map's ``map_states`` row: manifest, arrays npz (``-0.0`` patches included), activity, counts."""
    manifest: dict[str, Any] = {}
    extra: dict[str, np.ndarray] = {}
    for key, value in snapshot.items():
        array = np.asarray(value)
        place = PLACES.get(key, "arrays")
        manifest[key] = {"dtype": array.dtype.str, "shape": list(array.shape), "in": place}
        if place == "arrays":
            extra[key] = array
    for key in ROW_FLOAT_KEYS:
        patch = negative_zeros(snapshot[key])
        if patch.size:
            extra[NEGZERO_PREFIX + key] = patch
    last_stamp = _scalar(snapshot, "eng_last_stamp", math.nan)
    values = {
        "map_id": map_id,
        "lattice_rank": shapes.rank,
        "frames": int(_scalar(snapshot, "eng_frames", 0)),
        "last_stamp": None if math.isnan(last_stamp) else last_stamp,
        "current_template": int(_scalar(snapshot, "lv_current", -1)),
        "current_experience": int(_scalar(snapshot, "em_current", -1)),
        "n_templates": shapes.templates,
        "n_experiences": shapes.experiences,
        "n_links": shapes.links,
        "n_pose_cell_links": shapes.pc_links,
        "pc_activity": pack_raw(np.asarray(snapshot[ACTIVITY_KEY])),
        "arrays": pack_npz(share_arrays(conn, extra)),
        "manifest": manifest,
        "health": map_health(params, snapshot),
        "updated_at": utcnow(),
    }
    conn.execute(MapState.__table__.delete().where(MapState.map_id == map_id))
    conn.execute(insert(MapState).values(**values))


def assemble_snapshot(
    name: str, manifest: dict[str, Any], extra: dict[str, np.ndarray], pc_activity: bytes, built: dict[str, np.ndarray]
) -> dict[str, np.ndarray]:
    """Return the snapshot the manifest describes: each key from the rows read, the arrays blob or the activity.

    Dtype, shape and the bits of negative zeros are restored as saved (:func:`restore_negative_zeros`).
    """
    snapshot: dict[str, np.ndarray] = {}
    for key, info in manifest.items():
        dtype = np.dtype(info["dtype"])
        shape_k = tuple(int(v) for v in info["shape"])
        place = info["in"]
        if place == "arrays":
            if key not in extra:
                msg = f"map {name!r}: stored arrays lack {key!r}"
                raise CorruptStateError(msg)
            value = extra[key]
        elif place == "pc_activity":
            value = unpack_raw(pc_activity, dtype, shape_k)
        else:
            value = built[key]
        if value.size != math.prod(shape_k):
            msg = f"map {name!r}: {key!r} has {value.size} values, the manifest says shape {shape_k!r}"
            raise CorruptStateError(msg)
        array = np.array(value, dtype=dtype, copy=True).reshape(shape_k)
        patch = extra.get(NEGZERO_PREFIX + key)
        if patch is not None:
            restore_negative_zeros(array, patch)
        snapshot[key] = array
    return snapshot

"""Map state I/O: an engine snapshot (docs/architecture.md) ↔ the row tables and the ``map_states`` row.

Where each snapshot key goes:

=====================================================  =========================================
``lv_templates``, ``lv_means``, ``lv_origin``          ``templates`` (one row per template)
``pc_link_*``                                          ``pose_cell_links`` (row order kept: ``seq``)
``em_pose``, ``em_pc``, ``em_template``, ``em_stamp``,  ``experiences``
``em_origin``
``em_link_*``                                          ``links`` (row order kept: ``seq``; ``em_link_active``:
                                                      ``links.active``, true when a snapshot lacks it)
``pc_activity``                                        ``map_states.pc_activity`` (zlib, raw float64)
every other key (current template/experience,          ``map_states.arrays`` (compressed npz), so a
accumulators, VO profiles, gate, ``eng_*``, new keys)  key a newer engine adds is never lost
=====================================================  =========================================

``map_states.manifest`` records every key's dtype, shape and place; :func:`read_map_state` rebuilds
the same arrays bit for bit (the sign of ``-0.0`` in float columns, which SQLite drops, is kept as a
patch in the npz). Row tables hold no NaN: a state with NaN in a row-table float, or a non-finite
experience pose (its quaternion columns would be NaN), is refused.

Origins: ``lv_origin`` / ``em_origin`` are opaque tags; ``origins`` maps each tag to a session id
(the tag of a stored session is its id). Loaded snapshots carry session ids.

Stable identity: each template and experience row also carries (origin session, index within that
session). :func:`write_map_state` takes the indices as ``template_index`` / ``experience_index``: one
entry per row, where a negative entry — or a missing one, past the end of a shorter array — marks a
new row, which gets the next free index of its session (in row order). Without them, the snapshot must
extend the map's stored state (the engine only appends) and the stored identities are kept. After a
merge renumbers rows, pass the renumbered identity arrays (:class:`MapMeta` has the loaded ones; rows
of the running session that were never stored are -1).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt
from sqlalchemy import Connection, Update, bindparam, case, func, insert, or_, select, update
from sqlalchemy.orm import InstrumentedAttribute

from core.experience_map import per_experience_array
from core.se3 import quaternions_from_yaws
from mapserver.errors import StoreError
from mapserver.formats import LINK_KIND_CODES
from mapserver.store.arrays import (
    negative_zeros,
    pack_npz,
    pack_raw,
    restore_negative_zeros,
    unpack_npz,
    unpack_raw,
)
from mapserver.store.blobs import resolve_arrays, share_arrays
from mapserver.store.bulk import bulk_insert, fetch_tuples
from mapserver.store.errors import CorruptStateError, OwnershipError
from mapserver.store.health import map_health
from mapserver.store.maps import MapRecord, claim_map, get_map_by_id
from mapserver.store.models import (
    LINK_KIND_NAMES,
    Experience,
    Link,
    Map,
    MapState,
    PoseCellLink,
    Session,
    Template,
    utcnow,
)
from mapserver.store.sessions import SessionRecord, sessions_of_map

TEMPLATE_KEYS = ("lv_templates", "lv_means", "lv_origin")
POSE_CELL_LINK_KEYS = ("pc_link_template", "pc_link_coords", "pc_link_strength", "pc_link_decay")
EXPERIENCE_KEYS = ("em_pose", "em_pc", "em_template", "em_stamp", "em_origin")
LINK_KEYS = ("em_link_from", "em_link_to", "em_link_transform", "em_link_dt", "em_link_distance", "em_link_kind")
ACTIVITY_KEY = "pc_activity"

PLACES: dict[str, str] = {
    **dict.fromkeys(TEMPLATE_KEYS, "templates"),
    **dict.fromkeys(POSE_CELL_LINK_KEYS, "pose_cell_links"),
    **dict.fromkeys(EXPERIENCE_KEYS, "experiences"),
    **dict.fromkeys(LINK_KEYS, "links"),
    "em_link_active": "links",
    ACTIVITY_KEY: "pc_activity",
}
"""Snapshot key → where it is stored (keys not listed go to the ``arrays`` npz)."""

NEGZERO_PREFIX = "__negzero__."
_ROW_FLOAT_KEYS = (
    "lv_means",
    "pc_link_coords",
    "pc_link_strength",
    "pc_link_decay",
    "em_pose",
    "em_pc",
    "em_stamp",
    "em_link_transform",
    "em_link_dt",
    "em_link_distance",
)
_KEY_LIMIT = 1 << 32


@dataclass(frozen=True)
class MapMeta:
    """Who is who in a loaded map state.

    Attributes:
        map: the map's row.
        sessions: the map's sessions in creation order.
        template_session: (N,) origin session id of each template (row order).
        template_index: (N,) index of each template within its origin session.
        experience_session: (E,) origin session id of each experience.
        experience_index: (E,) index of each experience within its origin session.
    """

    map: MapRecord
    sessions: tuple[SessionRecord, ...]
    template_session: npt.NDArray[np.int64]
    template_index: npt.NDArray[np.int64]
    experience_session: npt.NDArray[np.int64]
    experience_index: npt.NDArray[np.int64]

    def session_names(self) -> dict[int, str]:
        """Return session id → session name (the ``session_name_by_origin`` of ``formats.map_json``)."""
        return {s.id: s.name for s in self.sessions}


@dataclass(frozen=True)
class MapContent:
    """A loaded map: parameters, engine snapshot and metadata."""

    params: dict[str, Any]
    snapshot: dict[str, np.ndarray]
    meta: MapMeta


@dataclass(frozen=True)
class WriteResult:
    """What :func:`write_map_state` stored: the map's new version and the stable identities it used."""

    map_id: int
    version: int
    template_session: npt.NDArray[np.int64]
    template_index: npt.NDArray[np.int64]
    experience_session: npt.NDArray[np.int64]
    experience_index: npt.NDArray[np.int64]


# ------------------------------------------------------------------------------------------------ helpers


def plain_params(params: Any) -> dict[str, Any]:
    """Return parameters (a ``core.Params`` or a mapping) as a JSON-normalised dict.

    Raises:
        StoreError: a value is not JSON-serialisable.
    """
    values = params.to_dict() if hasattr(params, "to_dict") else dict(params)
    try:
        result: dict[str, Any] = json.loads(json.dumps(values, allow_nan=True))
    except (TypeError, ValueError) as err:
        msg = f"parameters cannot be stored as JSON: {err}"
        raise StoreError(msg) from err
    return result


def _array(snapshot: Mapping[str, npt.ArrayLike], key: str) -> np.ndarray:
    if key not in snapshot:
        msg = f"the snapshot lacks {key!r}"
        raise StoreError(msg)
    return np.asarray(snapshot[key])


def _pair_keys(sessions: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Return one int64 per (session, index) pair."""
    if sessions.size and (sessions.min() < 0 or sessions.max() >= 1 << 31):
        msg = "session ids must lie in [0, 2**31)"
        raise StoreError(msg)
    if indices.size and (indices.min() < 0 or indices.max() >= _KEY_LIMIT):
        msg = "identity indices must lie in [0, 2**32)"
        raise StoreError(msg)
    return sessions.astype(np.int64) * _KEY_LIMIT + indices.astype(np.int64)


def _map_tags(tags: np.ndarray, origins: Mapping[int, int], what: str) -> np.ndarray:
    """Translate origin tags into session ids."""
    tags = tags.astype(np.int64).reshape(-1)
    if tags.size == 0:
        return tags.copy()
    keys = np.array(sorted(origins), dtype=np.int64)
    values = np.array([origins[int(k)] for k in keys], dtype=np.int64)
    if keys.size == 0:
        msg = f"{what} carry origin tags but the map has no session"
        raise StoreError(msg)
    pos = np.clip(np.searchsorted(keys, tags), 0, keys.size - 1)
    ok = keys[pos] == tags
    if not np.all(ok):
        bad = sorted(set(tags[~ok].tolist()))[:5]
        msg = f"{what} carry origin tag(s) {bad!r} that name no session of the map"
        raise StoreError(msg)
    return values[pos]


@dataclass(frozen=True)
class _Shapes:
    templates: int
    height: int
    width: int
    experiences: int
    links: int
    pc_links: int
    rank: int


def _check_snapshot(snapshot: Mapping[str, npt.ArrayLike]) -> _Shapes:
    """Validate the row-table arrays' shapes and values; return the sizes."""
    for key in snapshot:
        if key.startswith("__"):
            msg = f"snapshot key {key!r} is reserved (keys starting with '__')"
            raise StoreError(msg)
    shapes = _check_shapes(snapshot)
    _check_values(snapshot, shapes)
    return shapes


def _check_shapes(snapshot: Mapping[str, npt.ArrayLike]) -> _Shapes:
    """Check every row-table array's shape against the templates, experiences, links and pose-cell links."""
    templates = _array(snapshot, "lv_templates")
    if templates.ndim != 3 or templates.dtype != np.float32:
        msg = f"lv_templates must be float32 (N, ty, tx), got {templates.dtype} {templates.shape!r}"
        raise StoreError(msg)
    n, h, w = templates.shape
    activity = _array(snapshot, ACTIVITY_KEY)
    rank = activity.ndim
    if rank not in (3, 4):
        msg = f"pc_activity must have 3 or 4 dimensions, got shape {activity.shape!r}"
        raise StoreError(msg)
    e = _array(snapshot, "em_pose").reshape(-1, 4).shape[0]
    k = _array(snapshot, "em_link_from").reshape(-1).shape[0]
    lpc = _array(snapshot, "pc_link_template").reshape(-1).shape[0]
    expected = {
        "lv_means": (n,), "lv_origin": (n,),
        "pc_link_coords": (lpc, rank), "pc_link_strength": (lpc,), "pc_link_decay": (lpc,),
        "em_pose": (e, 4), "em_pc": (e, rank), "em_template": (e,), "em_stamp": (e,), "em_origin": (e,),
        "em_link_to": (k,), "em_link_transform": (k, 4), "em_link_dt": (k,), "em_link_distance": (k,),
        "em_link_kind": (k,),
    }  # fmt: skip
    optional = {"em_link_active": (k,), "em_pc_lever": (e,)}
    expected.update({key: shape for key, shape in optional.items() if key in snapshot})
    for key, shape in expected.items():
        got = _array(snapshot, key).shape
        if got != shape:
            msg = f"snapshot {key!r} has shape {got!r}, expected {shape!r}"
            raise StoreError(msg)
    return _Shapes(n, h, w, e, k, lpc, rank)


def _check_values(snapshot: Mapping[str, npt.ArrayLike], shapes: _Shapes) -> None:
    """Check the values: no NaN in a row table, finite poses, known link kinds, ids in range, levers ≥ 0."""
    for key in _ROW_FLOAT_KEYS:
        values = _array(snapshot, key)
        if values.size and not np.all(np.isfinite(values) | np.isinf(values)):
            row = int(np.flatnonzero(np.isnan(values.reshape(len(values), -1)).any(axis=1))[0])
            msg = f"snapshot {key!r} holds NaN (row {row}); a map with NaN cannot be stored"
            raise StoreError(msg)
    pose = _array(snapshot, "em_pose")
    if pose.size and not np.all(np.isfinite(pose)):
        row = int(np.flatnonzero(~np.isfinite(pose).all(axis=1))[0])
        msg = f"experience {row} has a non-finite pose {pose[row].tolist()!r}; a map with it cannot be stored"
        raise StoreError(msg)
    kinds = _array(snapshot, "em_link_kind")
    if kinds.size and (kinds.min() < 0 or kinds.max() >= len(LINK_KIND_NAMES)):
        msg = f"em_link_kind holds unknown codes {sorted(set(kinds.tolist()) - set(range(len(LINK_KIND_NAMES))))!r}"
        raise StoreError(msg)
    for key, limit, what in (
        ("em_template", shapes.templates, "templates"),
        ("pc_link_template", shapes.templates, "templates"),
        ("em_link_from", shapes.experiences, "experiences"),
        ("em_link_to", shapes.experiences, "experiences"),
    ):
        values = _array(snapshot, key)
        if values.size and (values.min() < 0 or values.max() >= limit):
            msg = f"snapshot {key!r} refers to {what} outside [0, {limit})"
            raise StoreError(msg)
    levers = _array(snapshot, "em_pc_lever") if "em_pc_lever" in snapshot else np.zeros(0)
    if levers.size and not (np.all(np.isfinite(levers)) and levers.min() >= 0.0):
        msg = "snapshot 'em_pc_lever' must hold finite lattice distances ≥ 0 (a merge's lever arms)"
        raise StoreError(msg)


# ------------------------------------------------------------------------------------------------ identities


def _identities(
    conn: Connection,
    table: type[Template] | type[Experience],
    map_id: int,
    sessions: np.ndarray,
    given: npt.ArrayLike | None,
    what: str,
) -> np.ndarray:
    """Return the index-within-session of every row (see the module docstring)."""
    n = sessions.shape[0]
    if given is None:
        rows = conn.execute(
            select(table.session_id, table.origin_index).where(table.map_id == map_id).order_by(table.local_id)
        ).all()
        stored = np.array(rows, dtype=np.int64).reshape(-1, 2)
        if stored.shape[0] > n or not np.array_equal(stored[:, 0], sessions[: stored.shape[0]]):
            msg = (
                f"the snapshot's {what} do not extend the map's stored {what} "
                f"({stored.shape[0]} stored, {n} given); pass their identities ({what[:-1]}_index)"
            )
            raise StoreError(msg)
        prefix = stored[:, 1]
    else:
        prefix = np.asarray(given, dtype=np.int64).reshape(-1)
        if prefix.shape[0] > n:
            msg = f"{prefix.shape[0]} {what[:-1]} identities given for {n} {what}"
            raise StoreError(msg)
    p = prefix.shape[0]
    indices = np.full(n, -1, dtype=np.int64)
    indices[:p] = prefix
    fresh_rows = np.flatnonzero(indices < 0)
    if fresh_rows.size:
        fresh = sessions[fresh_rows]
        unique = np.unique(fresh)
        maxima = {
            int(s): int(m)
            for s, m in conn.execute(
                select(table.session_id, func.max(table.origin_index))
                .where(table.session_id.in_(unique.tolist()))
                .group_by(table.session_id)
            ).all()
            if m is not None
        }
        known = indices >= 0
        base = np.empty(unique.shape[0], dtype=np.int64)
        for j, s in enumerate(unique.tolist()):
            in_given = indices[known & (sessions == s)]
            base[j] = max(maxima.get(s, -1), int(in_given.max(initial=-1))) + 1
        order = np.argsort(fresh, kind="stable")
        ordered = fresh[order]
        ranks_sorted = np.arange(ordered.shape[0]) - np.searchsorted(ordered, ordered, side="left")
        ranks = np.empty_like(ranks_sorted)
        ranks[order] = ranks_sorted
        indices[fresh_rows] = base[np.searchsorted(unique, fresh)] + ranks
    keys = _pair_keys(sessions, indices)
    if np.unique(keys).shape[0] != n:
        msg = f"two {what} of the snapshot have the same identity (session, index)"
        raise StoreError(msg)
    return indices


# ------------------------------------------------------------------------------------------------ writing


def frontend_of(params: Any) -> str:
    """Return the view front-end named by engine parameters (``core.Params`` or its dict)."""
    value = params.get("frontend", "lvc") if isinstance(params, Mapping) else getattr(params, "frontend", "lvc")
    return str(value)


def _rewrite_reexpressed_templates(
    conn: Connection, templates: np.ndarray, means: np.ndarray, sessions: np.ndarray, indices: np.ndarray
) -> None:
    """Rewrite stored template rows whose content the snapshot changed (``sdr-htm`` view cells only).

    Templates are otherwise immutable (:func:`_sync_templates` refuses a row stored with other data). An
    ``sdr-htm`` view cell is re-expressed when its session merges into a stored map: its prototype becomes the
    stored map's cortex's cells (``mapserver.merge.cortex``), so a session stored partially before its merge
    (``--stop-after``) holds rows whose content the merged snapshot replaces.
    """
    n = templates.shape[0]
    if n == 0:
        return
    data = np.ascontiguousarray(templates, dtype="<f4")
    stored = conn.execute(
        select(Template.session_id, Template.origin_index, Template.mean, Template.data).where(
            Template.session_id.in_(np.unique(sessions).tolist())
        )
    ).all()
    by_key = {(int(r[0]), int(r[1])): (float(r[2]), bytes(r[3])) for r in stored}
    changed = []
    for i in range(n):
        key = (int(sessions[i]), int(indices[i]))
        row = by_key.get(key)
        if row is not None and (row[0] != float(means[i]) or row[1] != data[i].tobytes()):
            changed.append({"b_s": key[0], "b_i": key[1], "b_mean": float(means[i]), "b_data": data[i].tobytes(),
                            "b_h": int(templates.shape[1]), "b_w": int(templates.shape[2])})  # fmt: skip
    if changed:
        conn.execute(
            _template_update(mean=bindparam("b_mean"), data=bindparam("b_data"), height=bindparam("b_h"),
                             width=bindparam("b_w")),
            changed,
        )  # fmt: skip


def _template_update(**values: Any) -> Update:
    """Return an executemany UPDATE of template rows by identity (``b_s``, ``b_i``) setting ``values``."""
    return (
        update(Template)
        .where(Template.session_id == bindparam("b_s"), Template.origin_index == bindparam("b_i"))
        .values(**values)
    )


def _sync_templates(
    conn: Connection, map_id: int, templates: np.ndarray, means: np.ndarray, sessions: np.ndarray, indices: np.ndarray
) -> None:
    """Make the map's template rows match the snapshot (insert new, renumber moved, detach dropped)."""
    n, h, w = templates.shape
    keys = _pair_keys(sessions, indices)
    existing, existing_mean = _stored_template_rows(conn, map_id, sessions)
    ekeys = _pair_keys(existing[:, 0], existing[:, 1])
    found = np.zeros(n, dtype=bool)
    e_map = np.full(n, -1, dtype=np.int64)
    e_local = np.full(n, -1, dtype=np.int64)
    if ekeys.size:
        order = np.argsort(ekeys)
        pos = np.clip(np.searchsorted(ekeys[order], keys), 0, ekeys.size - 1)
        row = order[pos]
        found = ekeys[row] == keys
        e_map = np.where(found, existing[row, 2], -1)
        e_local = np.where(found, existing[row, 3], -1)
        differs = found & (
            (existing[row, 4] != h) | (existing[row, 5] != w) | (existing_mean[row] != means.astype(np.float64))
        )
        if np.any(differs):
            i = int(np.flatnonzero(differs)[0])
            msg = f"template {i} (session {int(sessions[i])}, index {int(indices[i])}) is stored with other data"
            raise StoreError(msg)
    held = found & (e_map != -1) & (e_map != map_id)
    if np.any(held):
        i = int(np.flatnonzero(held)[0])
        msg = (
            f"template {i} (session {int(sessions[i])}, index {int(indices[i])}) belongs to map id "
            f"{int(e_map[i])}; drop or archive that map first"
        )
        raise OwnershipError(msg)
    move = found & ~((e_map == map_id) & (e_local == np.arange(n, dtype=np.int64)))
    dropped = (existing[:, 2] == map_id) & ~np.isin(ekeys, keys)
    _detach_and_move_templates(conn, map_id, sessions, indices, existing[dropped, :2], move, move & (e_map == map_id))
    _insert_templates(conn, map_id, templates, means, sessions, indices, np.flatnonzero(~found))


def _stored_template_rows(conn: Connection, map_id: int, sessions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the stored template rows of the map or of ``sessions``: (R, 6) identity/placement/shape, (R,) means."""
    unique_sessions = np.unique(sessions).tolist()
    where = Template.map_id == map_id
    if unique_sessions:
        where = or_(where, Template.session_id.in_(unique_sessions))
    rows = conn.execute(
        select(
            Template.session_id,
            Template.origin_index,
            func.coalesce(Template.map_id, -1),
            func.coalesce(Template.local_id, -1),
            Template.height,
            Template.width,
            Template.mean,
        ).where(where)
    ).all()
    existing = np.array([r[:6] for r in rows], dtype=np.int64).reshape(-1, 6)
    existing_mean = np.array([r[6] for r in rows], dtype=np.float64)
    return existing, existing_mean


def _detach_and_move_templates(
    conn: Connection, map_id: int, sessions: np.ndarray, indices: np.ndarray, dropped: np.ndarray,
    move: np.ndarray, moved_here: np.ndarray,
) -> None:  # fmt: skip
    """Detach the map's dropped rows (and its own moved ones), then place moved rows at their new local ids."""
    detach = [(int(s), int(i)) for s, i in dropped.tolist()]
    detach += [(int(sessions[i]), int(indices[i])) for i in np.flatnonzero(moved_here).tolist()]
    if detach:
        conn.execute(_template_update(map_id=None, local_id=None), [{"b_s": s, "b_i": i} for s, i in detach])
    moved = np.flatnonzero(move)
    if moved.size:
        conn.execute(
            _template_update(map_id=bindparam("b_m"), local_id=bindparam("b_l")),
            [
                {"b_s": int(sessions[i]), "b_i": int(indices[i]), "b_m": map_id, "b_l": int(i)}
                for i in moved.tolist()
            ],
        )


def _insert_templates(
    conn: Connection, map_id: int, templates: np.ndarray, means: np.ndarray, sessions: np.ndarray,
    indices: np.ndarray, new: np.ndarray,
) -> None:  # fmt: skip
    """Insert the snapshot's templates ``new`` (rows not stored yet) into the map."""
    if new.size:
        _n, h, w = templates.shape
        data = np.ascontiguousarray(templates, dtype="<f4")
        mean_list = means.astype(np.float64).tolist()
        sess_list = sessions.tolist()
        idx_list = indices.tolist()
        rows_out = [
            (sess_list[i], idx_list[i], map_id, i, h, w, mean_list[i], data[i].tobytes()) for i in new.tolist()
        ]
        bulk_insert(
            conn,
            Template.__table__,
            ("session_id", "origin_index", "map_id", "local_id", "height", "width", "mean", "data"),
            rows_out,
        )


def _coords(pc: np.ndarray, rank: int) -> tuple[list[float], list[float], list[float | None], list[float]]:
    """Split (R, D) lattice coordinates into the pc_x, pc_y, pc_z (None for D = 3), pc_th columns."""
    x = pc[:, 0].tolist()
    y = pc[:, 1].tolist()
    z: list[float | None] = pc[:, 2].tolist() if rank == 4 else [None] * pc.shape[0]
    th = pc[:, rank - 1].tolist()
    return x, y, z, th


def _insert_pose_cell_links(conn: Connection, map_id: int, snapshot: Mapping[str, Any], rank: int) -> None:
    template = np.asarray(snapshot["pc_link_template"]).astype(np.int64).reshape(-1)
    coords = np.asarray(snapshot["pc_link_coords"], dtype=np.float64).reshape(-1, rank)
    x, y, z, th = _coords(coords, rank)
    count = template.shape[0]
    rows = list(
        zip(
            [map_id] * count,
            range(count),
            template.tolist(),
            x,
            y,
            z,
            th,
            np.asarray(snapshot["pc_link_strength"], dtype=np.float64).tolist(),
            np.asarray(snapshot["pc_link_decay"], dtype=np.float64).tolist(),
            strict=True,
        )
    )
    columns = ("map_id", "seq", "template", "pc_x", "pc_y", "pc_z", "pc_th", "strength", "decay")
    bulk_insert(conn, PoseCellLink.__table__, columns, rows)


def _insert_experiences(
    conn: Connection,
    map_id: int,
    snapshot: Mapping[str, Any],
    rank: int,
    sessions: np.ndarray,
    indices: np.ndarray,
) -> None:
    pose = np.asarray(snapshot["em_pose"], dtype=np.float64).reshape(-1, 4)
    count = pose.shape[0]
    qx, qy, qz, qw = quaternions_from_yaws(pose[:, 3]).T.tolist()
    x, y, z, th = _coords(np.asarray(snapshot["em_pc"], dtype=np.float64).reshape(-1, rank), rank)
    rows = list(
        zip(
            [map_id] * count,
            range(count),
            sessions.tolist(),
            indices.tolist(),
            pose[:, 0].tolist(),
            pose[:, 1].tolist(),
            pose[:, 2].tolist(),
            qx,
            qy,
            qz,
            qw,
            pose[:, 3].tolist(),
            x,
            y,
            z,
            th,
            np.asarray(snapshot["em_template"]).astype(np.int64).tolist(),
            np.asarray(snapshot["em_stamp"], dtype=np.float64).tolist(),
            strict=True,
        )
    )
    columns = (
        "map_id", "local_id", "session_id", "origin_index", "x", "y", "z", "qx", "qy", "qz", "qw", "yaw",
        "pc_x", "pc_y", "pc_z", "pc_th", "template", "stamp",
    )  # fmt: skip
    bulk_insert(conn, Experience.__table__, columns, rows)


def _insert_links(conn: Connection, map_id: int, snapshot: Mapping[str, Any]) -> None:
    source = np.asarray(snapshot["em_link_from"]).astype(np.int64).reshape(-1)
    count = source.shape[0]
    transform = np.asarray(snapshot["em_link_transform"], dtype=np.float64).reshape(-1, 4)
    names = np.asarray(LINK_KIND_NAMES, dtype=object)[np.asarray(snapshot["em_link_kind"]).astype(np.int64)]
    active = np.asarray(snapshot.get("em_link_active", np.ones(count, dtype=bool)), dtype=bool).reshape(-1)
    rows = list(
        zip(
            [map_id] * count,
            range(count),
            source.tolist(),
            np.asarray(snapshot["em_link_to"]).astype(np.int64).tolist(),
            transform[:, 0].tolist(),
            transform[:, 1].tolist(),
            transform[:, 2].tolist(),
            transform[:, 3].tolist(),
            np.asarray(snapshot["em_link_dt"], dtype=np.float64).tolist(),
            np.asarray(snapshot["em_link_distance"], dtype=np.float64).tolist(),
            names.tolist(),
            active.tolist(),
            strict=True,
        )
    )
    columns = ("map_id", "seq", "from_id", "to_id", "dx", "dy", "dz", "dyaw", "dt", "distance", "kind", "active")
    bulk_insert(conn, Link.__table__, columns, rows)


def _scalar(snapshot: Mapping[str, Any], key: str, default: float) -> float:
    if key not in snapshot:
        return default
    value = np.asarray(snapshot[key])
    return float(value) if value.size == 1 else default


def _with_link_status(snapshot: Mapping[str, Any]) -> Mapping[str, Any]:
    """Return ``snapshot`` with ``em_link_active`` fitted to the links, as the engine reads it.

    A snapshot whose links were replaced may carry a status array of another length: links past
    its end are on, statuses past the last link are dropped (``ExperienceMap.restore``'s rule).
    """
    if "em_link_active" not in snapshot:
        return snapshot
    count = np.asarray(snapshot["em_link_from"]).reshape(-1).shape[0]
    given = np.asarray(snapshot["em_link_active"], dtype=bool).reshape(-1)
    if given.shape[0] == count:
        return snapshot
    active = np.ones(count, dtype=bool)
    active[: min(given.size, count)] = given[:count]
    return {**snapshot, "em_link_active": active}


def _with_levers(snapshot: Mapping[str, Any]) -> Mapping[str, Any]:
    """Return ``snapshot`` with ``em_pc_lever`` fitted to the experiences, as the engine reads it.

    A snapshot whose experiences were replaced (an importer starting from an empty engine's snapshot) may
    carry levers of another length: experiences past its end have lever 0 (no merge moved them), levers past
    the last experience are dropped (``ExperienceMap.restore``'s rule).
    """
    if "em_pc_lever" not in snapshot:
        return snapshot
    count = np.asarray(snapshot["em_pose"]).reshape(-1, 4).shape[0]
    if np.asarray(snapshot["em_pc_lever"]).reshape(-1).shape[0] == count:
        return snapshot
    return {**snapshot, "em_pc_lever": per_experience_array(snapshot, "em_pc_lever", count)}


def _write_state_row(
    conn: Connection, map_id: int, snapshot: Mapping[str, Any], shapes: _Shapes, params: Any
) -> None:
    manifest: dict[str, Any] = {}
    extra: dict[str, np.ndarray] = {}
    for key, value in snapshot.items():
        array = np.asarray(value)
        place = PLACES.get(key, "arrays")
        manifest[key] = {"dtype": array.dtype.str, "shape": list(array.shape), "in": place}
        if place == "arrays":
            extra[key] = array
    for key in _ROW_FLOAT_KEYS:
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


def write_map_state(
    *,
    conn: Connection,
    map_id: int,
    expected_version: int,
    params: Any,
    snapshot: Mapping[str, npt.ArrayLike],
    session_ids: Sequence[int],
    origins: Mapping[int, int] | None = None,
    template_index: npt.ArrayLike | None = None,
    experience_index: npt.ArrayLike | None = None,
) -> WriteResult:
    """Replace a map's stored state with ``snapshot``, inside the caller's write transaction.

    First claims the map (:func:`~mapserver.store.maps.claim_map`: version check and bump, row lock),
    then rewrites experiences, links and pose-cell links, syncs template rows (immutable; new ones
    inserted, renumbered ones updated, dropped ones detached), writes the state row, and makes
    ``session_ids`` the map's sessions (sessions it had before and not listed are detached).

    Args:
        conn: a connection in a write transaction (``Database.write()``).
        map_id: the map.
        expected_version: the version the snapshot was built from (0 for a map just created).
        params: the engine parameters (``core.Params`` or its dict).
        snapshot: ``Engine.snapshot()`` arrays (plus any extra keys; keys starting ``__`` are reserved).
        session_ids: the map's sessions, all stored already.
        origins: origin tag → session id for ``lv_origin``/``em_origin`` (default: each id is its tag).
        template_index: identities of the first templates (see the module docstring).
        experience_index: identities of the first experiences.

    Returns:
        The new version and the identities used.

    Raises:
        StaleMapError: the map's version is not ``expected_version``.
        OwnershipError: a template or experience of the snapshot belongs to another map.
        StoreError: the snapshot is malformed, has NaN in a row table, or tags that name no session.
    """
    snapshot = _with_levers(_with_link_status(snapshot))
    version = claim_map(conn=conn, map_id=map_id, expected_version=expected_version)
    shapes = _check_snapshot(snapshot)
    ids = [int(s) for s in session_ids]
    rows = _snapshot_identities(conn, map_id, snapshot, ids, origins, template_index, experience_index)
    _replace_rows(conn, map_id, snapshot, shapes, params, rows)
    _write_state_row(conn, map_id, snapshot, shapes, params)
    conn.execute(update(Map).where(Map.id == map_id).values(params=plain_params(params)))
    conn.execute(update(Session).where(Session.map_id == map_id, Session.id.not_in(ids)).values(map_id=None))
    if ids:
        conn.execute(update(Session).where(Session.id.in_(ids)).values(map_id=map_id))
    return WriteResult(map_id, version, *rows)


class _SnapshotIdentities(NamedTuple):
    """The stable identity (session, index) of every template and experience row of a snapshot."""

    template_sessions: npt.NDArray[np.int64]
    template_index: npt.NDArray[np.int64]
    experience_sessions: npt.NDArray[np.int64]
    experience_index: npt.NDArray[np.int64]


def _snapshot_identities(
    conn: Connection, map_id: int, snapshot: Mapping[str, Any], ids: list[int], origins: Mapping[int, int] | None,
    template_index: npt.ArrayLike | None, experience_index: npt.ArrayLike | None,
) -> _SnapshotIdentities:  # fmt: skip
    """Return the snapshot rows' identities, refusing tags, sessions and owners the map cannot take."""
    tag_map = dict(origins) if origins is not None else {s: s for s in ids}
    unknown = sorted(set(tag_map.values()) - set(ids))
    if unknown:
        msg = f"origins name session(s) {unknown!r} that are not among the map's sessions {ids!r}"
        raise StoreError(msg)
    _check_sessions_exist(conn, ids)
    template_sessions = _map_tags(np.asarray(snapshot["lv_origin"]), tag_map, "templates")
    experience_sessions = _map_tags(np.asarray(snapshot["em_origin"]), tag_map, "experiences")
    _check_session_owners(conn, map_id, np.union1d(template_sessions, experience_sessions))
    t_index = _identities(conn, Template, map_id, template_sessions, template_index, "templates")
    e_index = _identities(conn, Experience, map_id, experience_sessions, experience_index, "experiences")
    return _SnapshotIdentities(template_sessions, t_index, experience_sessions, e_index)


def _replace_rows(
    conn: Connection, map_id: int, snapshot: Mapping[str, Any], shapes: _Shapes, params: Any, rows: _SnapshotIdentities
) -> None:
    """Rewrite the map's experience, link and pose-cell link rows and sync its template rows to the snapshot."""
    for table in (Link, PoseCellLink, Experience):
        conn.execute(table.__table__.delete().where(table.map_id == map_id))
    _check_experience_owners(conn, map_id, rows.experience_sessions, rows.experience_index)
    templates, means = np.asarray(snapshot["lv_templates"]), np.asarray(snapshot["lv_means"])
    if frontend_of(params) == "sdr-htm":
        _rewrite_reexpressed_templates(conn, templates, means, rows.template_sessions, rows.template_index)
    _sync_templates(conn, map_id, templates, means, rows.template_sessions, rows.template_index)
    _insert_pose_cell_links(conn, map_id, snapshot, shapes.rank)
    _insert_experiences(conn, map_id, snapshot, shapes.rank, rows.experience_sessions, rows.experience_index)
    _insert_links(conn, map_id, snapshot)


def _check_sessions_exist(conn: Connection, ids: Sequence[int]) -> None:
    """Refuse session ids that are not stored (rows reference them; SQLite bulk writes skip foreign-key checks)."""
    wanted = sorted(set(ids))
    if not wanted:
        return
    found = set(conn.execute(select(Session.id).where(Session.id.in_(wanted))).scalars())
    missing = [s for s in wanted if s not in found]
    if missing:
        msg = f"session id(s) {missing!r} are not stored"
        raise StoreError(msg)


def _check_session_owners(conn: Connection, map_id: int, sessions: np.ndarray) -> None:
    """Refuse content of sessions whose templates or experiences another map still holds."""
    ids = sessions.astype(np.int64).tolist()
    if not ids:
        return
    for table, what in ((Template, "templates"), (Experience, "experiences")):
        row = conn.execute(
            select(table.session_id, table.map_id)
            .where(table.session_id.in_(ids), table.map_id.is_not(None), table.map_id != map_id)
            .limit(1)
        ).first()
        if row is not None:
            msg = (
                f"session {int(row[0])} has {what} in map id {row[1]}; a session's content lives in one map: "
                "drop or archive that map first"
            )
            raise OwnershipError(msg)


def _check_experience_owners(conn: Connection, map_id: int, sessions: np.ndarray, indices: np.ndarray) -> None:
    unique_sessions = np.unique(sessions).tolist()
    if not unique_sessions:
        return
    rows = conn.execute(
        select(Experience.session_id, Experience.origin_index, Experience.map_id).where(
            Experience.session_id.in_(unique_sessions), Experience.map_id != map_id
        )
    ).all()
    if not rows:
        return
    other = np.array(rows, dtype=np.int64).reshape(-1, 3)
    clash = np.isin(_pair_keys(sessions, indices), _pair_keys(other[:, 0], other[:, 1]))
    if np.any(clash):
        i = int(np.flatnonzero(clash)[0])
        holder_rows = other[(other[:, 0] == sessions[i]) & (other[:, 1] == indices[i])]
        holder = int(holder_rows[0, 2])
        msg = (
            f"experience {i} (session {int(sessions[i])}, index {int(indices[i])}) belongs to map id {holder}; "
            "drop or archive that map first"
        )
        raise OwnershipError(msg)


# ------------------------------------------------------------------------------------------------ reading


def _column_block(rows: Sequence[Any], columns: int) -> np.ndarray:
    return np.array(rows, dtype=np.float64).reshape(-1, columns)


def read_map_templates(*, conn: Connection, map_id: int) -> np.ndarray:
    """Return a stored map's templates (N, ty, tx) float32 in id order, without the rest of its state."""
    rows = fetch_tuples(
        conn,
        select(Template.height, Template.width, Template.data).where(Template.map_id == map_id)
        .order_by(Template.local_id),
    )  # fmt: skip
    if not rows:
        return np.zeros((0, 0, 0), dtype=np.float32)
    h, w = int(rows[0][0]), int(rows[0][1])
    return np.frombuffer(b"".join(r[2] for r in rows), dtype="<f4").reshape(len(rows), h, w)


def read_map_state(*, conn: Connection, map_id: int) -> MapContent:
    """Load a map's state exactly as :func:`write_map_state` stored it.

    Args:
        conn: a connection in a read (or write) transaction.
        map_id: the map.

    Returns:
        Parameters, snapshot (the same keys, dtypes, shapes and bits as saved; origins are session ids)
        and metadata (sessions, stable identities).

    Raises:
        UnknownMapError: no such map.
        CorruptStateError: the map has no state or its rows disagree with the manifest.
    """
    record = get_map_by_id(conn=conn, map_id=map_id)
    state = conn.execute(
        select(MapState.manifest, MapState.arrays, MapState.pc_activity, MapState.lattice_rank).where(
            MapState.map_id == map_id
        )
    ).first()
    if state is None:
        msg = f"map {record.name!r} has no stored state"
        raise CorruptStateError(msg)
    manifest: dict[str, Any] = dict(state[0])
    rank = int(state[3])
    built: dict[str, np.ndarray] = {}
    template_session, template_index = _read_templates(conn, record.name, map_id, manifest, built)
    _read_pose_cell_links(conn, map_id, rank, built)
    experience_session, experience_index = _read_experiences(conn, map_id, rank, built)
    _read_links(conn, map_id, built)
    arrays = resolve_arrays(conn, unpack_npz(state[1]), f"map {record.name!r}")
    snapshot = _assemble_snapshot(record.name, manifest, arrays, state[2], built)
    sessions = tuple(sessions_of_map(conn=conn, map_id=map_id))
    meta = MapMeta(record, sessions, template_session, template_index, experience_session, experience_index)
    return MapContent(dict(record.params), snapshot, meta)


def _read_templates(
    conn: Connection, name: str, map_id: int, manifest: dict[str, Any], built: dict[str, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Read the LVC templates into ``built`` (``lv_*``); return each template's session id and origin index."""
    rows = fetch_tuples(
        conn,
        select(
            Template.session_id, Template.origin_index, Template.local_id, Template.height, Template.width,
            Template.mean, Template.data,
        )
        .where(Template.map_id == map_id)
        .order_by(Template.local_id),
    )  # fmt: skip
    n = len(rows)
    head = np.array([r[:5] for r in rows], dtype=np.int64).reshape(-1, 5)
    if not np.array_equal(head[:, 2], np.arange(n)):
        msg = f"map {name!r}: template local ids are not 0..{n - 1}"
        raise CorruptStateError(msg)
    shape = manifest.get("lv_templates", {}).get("shape", [0, 0, 0])
    h, w = (int(head[0, 3]), int(head[0, 4])) if n else (int(shape[1]), int(shape[2]))
    blob = b"".join(r[6] for r in rows)
    built["lv_templates"] = np.frombuffer(blob, dtype="<f4").reshape(n, h, w)
    built["lv_means"] = np.array([r[5] for r in rows], dtype=np.float64)
    built["lv_origin"] = head[:, 0].copy()
    return head[:, 0].copy(), head[:, 1].copy()


def _read_pose_cell_links(conn: Connection, map_id: int, rank: int, built: dict[str, np.ndarray]) -> None:
    """Read the LVC→pose-cell links into ``built`` (``pc_link_*``; coordinates of the lattice's ``rank``)."""
    pc_columns: list[InstrumentedAttribute[float | None]] = [
        PoseCellLink.template, PoseCellLink.pc_x, PoseCellLink.pc_y
    ]  # fmt: skip
    if rank == 4:
        pc_columns.append(PoseCellLink.pc_z)
    pc_columns += [PoseCellLink.pc_th, PoseCellLink.strength, PoseCellLink.decay]
    block = _column_block(
        fetch_tuples(conn, select(*pc_columns).where(PoseCellLink.map_id == map_id).order_by(PoseCellLink.seq)),
        len(pc_columns),
    )
    built["pc_link_template"] = block[:, 0].astype(np.int64)
    built["pc_link_coords"] = block[:, 1 : 1 + rank].copy()
    built["pc_link_strength"] = block[:, 1 + rank].copy()
    built["pc_link_decay"] = block[:, 2 + rank].copy()


def _read_experiences(
    conn: Connection, map_id: int, rank: int, built: dict[str, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Read the experiences into ``built`` (``em_pose`` … ``em_origin``); return their sessions and origin indices."""
    em_columns: list[InstrumentedAttribute[float | None]] = [
        Experience.session_id, Experience.origin_index, Experience.x, Experience.y, Experience.z, Experience.yaw,
        Experience.pc_x, Experience.pc_y,
    ]  # fmt: skip
    if rank == 4:
        em_columns.append(Experience.pc_z)
    em_columns += [Experience.pc_th, Experience.template, Experience.stamp]
    block = _column_block(
        fetch_tuples(conn, select(*em_columns).where(Experience.map_id == map_id).order_by(Experience.local_id)),
        len(em_columns),
    )
    experience_session = block[:, 0].astype(np.int64)
    built["em_pose"] = block[:, 2:6].copy()
    built["em_pc"] = block[:, 6 : 6 + rank].copy()
    built["em_template"] = block[:, 6 + rank].astype(np.int64)
    built["em_stamp"] = block[:, 7 + rank].copy()
    built["em_origin"] = experience_session.copy()
    return experience_session, block[:, 1].astype(np.int64)


def _read_links(conn: Connection, map_id: int, built: dict[str, np.ndarray]) -> None:
    """Read the experience links into ``built`` (``em_link_*``, kinds as their codes)."""
    kind_code = case(LINK_KIND_CODES, value=Link.kind, else_=-1)
    block = _column_block(
        fetch_tuples(
            conn,
            select(
                Link.from_id, Link.to_id, Link.dx, Link.dy, Link.dz, Link.dyaw, Link.dt, Link.distance, kind_code,
                Link.active,
            )
            .where(Link.map_id == map_id)
            .order_by(Link.seq),
        ),
        10,
    )
    built["em_link_from"] = block[:, 0].astype(np.int64)
    built["em_link_to"] = block[:, 1].astype(np.int64)
    built["em_link_transform"] = block[:, 2:6].copy()
    built["em_link_dt"] = block[:, 6].copy()
    built["em_link_distance"] = block[:, 7].copy()
    built["em_link_kind"] = block[:, 8].astype(np.int64)
    built["em_link_active"] = block[:, 9].astype(bool)


def _assemble_snapshot(
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


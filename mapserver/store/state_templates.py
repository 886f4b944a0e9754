"""Template rows of a stored map state: keep them in step with a snapshot.

Templates are immutable rows named by (session, index): new ones are inserted, moved ones renumbered, dropped ones
detached from the map (never deleted); only an ``sdr-htm`` view cell re-expressed by a merge is rewritten.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from sqlalchemy import Connection, Update, bindparam, func, or_, select, update

from mapserver.errors import StoreError
from mapserver.store.bulk import bulk_insert
from mapserver.store.errors import OwnershipError
from mapserver.store.models import Template
from mapserver.store.state_identities import pair_keys


def rewrite_reexpressed_templates(
    conn: Connection, templates: np.ndarray, means: np.ndarray, sessions: np.ndarray, indices: np.ndarray
) -> None:
    """Rewrite stored template rows whose content the snapshot changed (``sdr-htm`` view cells only).

    Templates are otherwise immutable (:func:`sync_templates` refuses a row stored with other data). An
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


def sync_templates(
    conn: Connection, map_id: int, templates: np.ndarray, means: np.ndarray, sessions: np.ndarray, indices: np.ndarray
) -> None:
    """Make the map's template rows match the snapshot (insert new, renumber moved, detach dropped)."""
    n, h, w = templates.shape
    keys = pair_keys(sessions, indices)
    existing, existing_mean = _stored_template_rows(conn, map_id, sessions)
    ekeys = pair_keys(existing[:, 0], existing[:, 1])
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

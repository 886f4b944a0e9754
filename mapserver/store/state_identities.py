"""Stable identities of a snapshot's rows: origin tags to sessions, (session, index) per row, and ownership.

See :mod:`mapserver.store.state` for the rules: given indices are kept, negative or missing ones get the next free
index of their session in row order; without indices the snapshot must extend the stored state. A session's
content lives in one map: content another map holds is refused (:class:`OwnershipError`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt
from sqlalchemy import Connection, func, select

from mapserver.errors import StoreError
from mapserver.store.errors import OwnershipError
from mapserver.store.models import Experience, Session, Template

_KEY_LIMIT = 1 << 32


def pair_keys(sessions: np.ndarray, indices: np.ndarray) -> np.ndarray:
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


class SnapshotIdentities(NamedTuple):
    """The stable identity (session, index) of every template and experience row of a snapshot."""

    template_sessions: npt.NDArray[np.int64]
    template_index: npt.NDArray[np.int64]
    experience_sessions: npt.NDArray[np.int64]
    experience_index: npt.NDArray[np.int64]


def snapshot_identities(
    conn: Connection, map_id: int, snapshot: Mapping[str, Any], ids: list[int], origins: Mapping[int, int] | None,
    template_index: npt.ArrayLike | None, experience_index: npt.ArrayLike | None,
) -> SnapshotIdentities:  # fmt: skip
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
    t_index = _row_identities(conn, Template, map_id, template_sessions, template_index, "templates")
    e_index = _row_identities(conn, Experience, map_id, experience_sessions, experience_index, "experiences")
    return SnapshotIdentities(template_sessions, t_index, experience_sessions, e_index)


def _row_identities(
    conn: Connection,
    table: type[Template] | type[Experience],
    map_id: int,
    sessions: np.ndarray,
    given: npt.ArrayLike | None,
    what: str,
) -> np.ndarray:
    """Return the index-within-session of every row (see :mod:`mapserver.store.state`)."""
    n = sessions.shape[0]
    indices = _known_indices(conn, table, map_id, sessions, given, what)
    _number_fresh_rows(conn, table, sessions, indices)
    keys = pair_keys(sessions, indices)
    if np.unique(keys).shape[0] != n:
        msg = f"two {what} of the snapshot have the same identity (session, index)"
        raise StoreError(msg)
    return indices


def _known_indices(
    conn: Connection,
    table: type[Template] | type[Experience],
    map_id: int,
    sessions: np.ndarray,
    given: npt.ArrayLike | None,
    what: str,
) -> np.ndarray:
    """Return (n,) indices: the given ones, or the stored rows' when none are given; -1 for the rest (new rows)."""
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
    return indices


def _number_fresh_rows(
    conn: Connection, table: type[Template] | type[Experience], sessions: np.ndarray, indices: np.ndarray
) -> None:
    """Give each row with a negative index, in row order, the next free index of its session (in place).

    A session's next free index is one past the highest it used, stored (in any map) or among ``indices``.
    """
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


def check_experience_owners(conn: Connection, map_id: int, sessions: np.ndarray, indices: np.ndarray) -> None:
    """Refuse experiences (``sessions``, ``indices``) that another map holds (:class:`OwnershipError`)."""
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
    clash = np.isin(pair_keys(sessions, indices), pair_keys(other[:, 0], other[:, 1]))
    if np.any(clash):
        i = int(np.flatnonzero(clash)[0])
        holder_rows = other[(other[:, 0] == sessions[i]) & (other[:, 1] == indices[i])]
        holder = int(holder_rows[0, 2])
        msg = (
            f"experience {i} (session {int(sessions[i])}, index {int(indices[i])}) belongs to map id {holder}; "
            "drop or archive that map first"
        )
        raise OwnershipError(msg)

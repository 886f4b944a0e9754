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

The steps live in one module each: :mod:`~mapserver.store.state_layout` (where each key goes),
:mod:`~mapserver.store.state_params` (parameters as stored), :mod:`~mapserver.store.state_validate` (checking a
snapshot), :mod:`~mapserver.store.state_identities` (stable identities and ownership),
:mod:`~mapserver.store.state_templates` (template rows), :mod:`~mapserver.store.state_rows_write` and
:mod:`~mapserver.store.state_rows_read` (the other row tables), :mod:`~mapserver.store.state_row` (the
``map_states`` row and the snapshot rebuilt from it). This module holds the two entry points and their records.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from sqlalchemy import Connection, select, update

from mapserver.store.arrays import unpack_npz
from mapserver.store.blobs import resolve_arrays
from mapserver.store.errors import CorruptStateError
from mapserver.store.maps import MapRecord, claim_map, get_map_by_id
from mapserver.store.models import Map, MapState, Session
from mapserver.store.sessions import SessionRecord, sessions_of_map
from mapserver.store.state_identities import snapshot_identities
from mapserver.store.state_layout import (
    ACTIVITY_KEY,
    EXPERIENCE_KEYS,
    LINK_KEYS,
    NEGZERO_PREFIX,
    PLACES,
    POSE_CELL_LINK_KEYS,
    TEMPLATE_KEYS,
)
from mapserver.store.state_params import frontend_of, plain_params
from mapserver.store.state_row import assemble_snapshot, write_state_row
from mapserver.store.state_rows_read import (
    read_experiences,
    read_links,
    read_map_templates,
    read_pose_cell_links,
    read_templates,
)
from mapserver.store.state_rows_write import replace_rows
from mapserver.store.state_validate import check_snapshot, with_levers, with_link_status

__all__ = [
    "ACTIVITY_KEY",
    "EXPERIENCE_KEYS",
    "LINK_KEYS",
    "NEGZERO_PREFIX",
    "PLACES",
    "POSE_CELL_LINK_KEYS",
    "TEMPLATE_KEYS",
    "MapContent",
    "MapMeta",
    "WriteResult",
    "frontend_of",
    "plain_params",
    "read_map_state",
    "read_map_templates",
    "write_map_state",
]


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
    snapshot = with_levers(with_link_status(snapshot))
    version = claim_map(conn=conn, map_id=map_id, expected_version=expected_version)
    shapes = check_snapshot(snapshot)
    ids = [int(s) for s in session_ids]
    rows = snapshot_identities(conn, map_id, snapshot, ids, origins, template_index, experience_index)
    replace_rows(conn, map_id, snapshot, shapes, params, rows)
    write_state_row(conn, map_id, snapshot, shapes, params)
    conn.execute(update(Map).where(Map.id == map_id).values(params=plain_params(params)))
    conn.execute(update(Session).where(Session.map_id == map_id, Session.id.not_in(ids)).values(map_id=None))
    if ids:
        conn.execute(update(Session).where(Session.id.in_(ids)).values(map_id=map_id))
    return WriteResult(map_id, version, *rows)


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
    template_session, template_index = read_templates(conn, record.name, map_id, manifest, built)
    read_pose_cell_links(conn, map_id, rank, built)
    experience_session, experience_index = read_experiences(conn, map_id, rank, built)
    read_links(conn, map_id, built)
    arrays = resolve_arrays(conn, unpack_npz(state[1]), f"map {record.name!r}")
    snapshot = assemble_snapshot(record.name, manifest, arrays, state[2], built)
    sessions = tuple(sessions_of_map(conn=conn, map_id=map_id))
    meta = MapMeta(record, sessions, template_session, template_index, experience_session, experience_index)
    return MapContent(dict(record.params), snapshot, meta)

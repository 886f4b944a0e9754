"""Whole-map save and load, each in one transaction (the API the pipeline, merge, import and tests use).

``load_map(save_map(s))`` returns ``s`` array for array (dtype, shape, bits); origins come back as
session ids (pass those ids as the tags, as every loaded snapshot does, and the round trip is the
identity). For saves that must share a transaction with other writes, use
:func:`mapserver.store.state.write_map_state` inside ``Database.write()``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy.typing as npt

from mapserver.store.db import Database
from mapserver.store.maps import create_map, get_map
from mapserver.store.sessions import NewSession, create_session
from mapserver.store.state import MapContent, WriteResult, plain_params, read_map_state, write_map_state


def save_map(
    db: Database,
    *,
    name: str,
    params: Any,
    snapshot: Mapping[str, npt.ArrayLike],
    sessions: Sequence[int | NewSession],
    expected_version: int | None = None,
    template_index: npt.ArrayLike | None = None,
    experience_index: npt.ArrayLike | None = None,
) -> WriteResult:
    """Save a whole map in one transaction.

    Args:
        db: the database.
        name: the map's name.
        params: the engine parameters (``core.Params`` or its dict).
        snapshot: ``Engine.snapshot()`` arrays.
        sessions: the map's sessions: stored session ids (their tag in the snapshot is the id) and/or
            :class:`NewSession` specs to create (their tag is ``spec.origin``).
        expected_version: None creates the map (the name must be free); an int updates the existing
            map, which must still be at that version.
        template_index: identities of the first templates (see :mod:`mapserver.store.state`).
        experience_index: identities of the first experiences.

    Returns:
        The map id, its new version and the identities stored.

    Raises:
        MapExistsError: ``expected_version`` is None and the name is taken.
        UnknownMapError: ``expected_version`` is given and no such map exists.
        StaleMapError: the map is not at ``expected_version``.
        StoreError: the snapshot cannot be stored (nothing is written).
    """
    with db.write(check_foreign_keys=False) as conn:  # write_map_state validates every reference
        if expected_version is None:
            record = create_map(conn=conn, name=name, params=plain_params(params))
            version = record.version
        else:
            record = get_map(conn=conn, name=name)
            version = expected_version
        ids: list[int] = []
        origins: dict[int, int] = {}
        for item in sessions:
            if isinstance(item, NewSession):
                created = create_session(conn=conn, spec=item)
                origins[item.origin] = created.id
                ids.append(created.id)
            else:
                ids.append(int(item))
                origins[int(item)] = int(item)
        return write_map_state(
            conn=conn,
            map_id=record.id,
            expected_version=version,
            params=params,
            snapshot=snapshot,
            session_ids=ids,
            origins=origins,
            template_index=template_index,
            experience_index=experience_index,
        )


def load_map(db: Database, *, name: str) -> MapContent:
    """Load a whole map (parameters, snapshot, metadata) from one consistent read.

    Raises:
        UnknownMapError: no such map.
        CorruptStateError: the stored state is inconsistent.
    """
    with db.read() as conn:
        record = get_map(conn=conn, name=name)
        return read_map_state(conn=conn, map_id=record.id)

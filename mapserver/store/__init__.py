"""The persistent map store: SQLAlchemy models, migrations, repositories, evidence, import and export.

Public surface::

    from mapserver.store import open_database, save_map, load_map
    with open_database("sqlite:///./var/mapserver.db") as db:      # creates an empty DB's schema
        save_map(db, name="lab", params=params, snapshot=engine.snapshot(), sessions=[NewSession(...)])
        content = load_map(db, name="lab")                          # params, snapshot, meta

Repository functions take keyword arguments only, the first being ``conn`` (a :data:`Connection` inside
``Database.write()`` or ``Database.read()``), so that callers compose them in one transaction. Every SQL
statement lives in this package: callers type their transaction handle as ``mapserver.store.Connection``
and use the constants below, never ``sqlalchemy`` or ``mapserver.store.models`` (``tests/test_layers.py``).
Design notes: docs/architecture.md, section "Store".
"""

from mapserver.store.db import DEFAULT_DB_URL, Connection, Database, create_db_engine, open_database
from mapserver.store.errors import (
    CorruptStateError,
    MapExistsError,
    OwnershipError,
    StaleMapError,
    UnknownMapError,
)
from mapserver.store.mapio import load_map, save_map
from mapserver.store.maps import (
    MapRecord,
    MapSummary,
    claim_map,
    clear_map,
    create_map,
    drop_map,
    find_map,
    get_map,
    get_map_by_id,
    list_maps,
    lock_atlas,
)
from mapserver.store.migrate import HEAD_REVISION, current_revision, downgrade, ensure_schema, upgrade
from mapserver.store.models import LINK_KIND_NAMES, MERGE_STATUSES, TOKEN_SCOPES, utcnow
from mapserver.store.sessions import NewSession, SessionRecord, find_session, get_session, sessions_of_map
from mapserver.store.state import MapContent, MapMeta, WriteResult, read_map_state, write_map_state

__all__ = [
    "DEFAULT_DB_URL",
    "HEAD_REVISION",
    "LINK_KIND_NAMES",
    "MERGE_STATUSES",
    "TOKEN_SCOPES",
    "Connection",
    "CorruptStateError",
    "Database",
    "MapContent",
    "MapExistsError",
    "MapMeta",
    "MapRecord",
    "MapSummary",
    "NewSession",
    "OwnershipError",
    "SessionRecord",
    "StaleMapError",
    "UnknownMapError",
    "WriteResult",
    "claim_map",
    "clear_map",
    "create_db_engine",
    "create_map",
    "current_revision",
    "downgrade",
    "drop_map",
    "ensure_schema",
    "find_map",
    "find_session",
    "get_map",
    "get_map_by_id",
    "get_session",
    "list_maps",
    "load_map",
    "lock_atlas",
    "open_database",
    "read_map_state",
    "save_map",
    "sessions_of_map",
    "upgrade",
    "utcnow",
    "write_map_state",
]

"""Schema migrations: Alembic driven programmatically (``mapserver db upgrade``, first use of an empty database).

The migration scripts live in ``migrations/`` at the repository root (``alembic.ini`` there is for
developers running ``alembic`` by hand). Upgrades run inside one transaction that first takes a lock
(SQLite ``BEGIN IMMEDIATE``; a PostgreSQL transaction-level advisory lock keyed on the schema), so two
processes opening the same empty database at once create the schema once.
"""

from __future__ import annotations

import logging
from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Connection, inspect, text
from sqlalchemy.exc import DBAPIError

from mapserver.errors import StoreError
from mapserver.store.db import Database

logger = logging.getLogger(__name__)

MIGRATIONS_DIR = Path(__file__).resolve().parents[2] / "migrations"
"""The Alembic script directory (``migrations/`` at the repository root)."""

HEAD_REVISION = "0010"
"""The revision the code expects (a test checks it is the script directory's head)."""

VERSION_TABLE = "alembic_version"


def alembic_config(connection: Connection | None = None) -> Config:
    """Return an Alembic config for :data:`MIGRATIONS_DIR`; ``connection`` is handed to ``env.py``."""
    if not (MIGRATIONS_DIR / "env.py").is_file():
        msg = f"the migration scripts are missing: {str(MIGRATIONS_DIR)!r}"
        raise StoreError(msg)
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    if connection is not None:
        config.attributes["connection"] = connection
    return config


def script_head() -> str | None:
    """Return the head revision of the migration scripts."""
    return ScriptDirectory.from_config(alembic_config()).get_current_head()


def current_revision(db: Database) -> str | None:
    """Return the database's schema revision (None for a database without the version table)."""
    with db.read() as conn:
        return _current(conn)


def _current(conn: Connection) -> str | None:
    if not inspect(conn).has_table(VERSION_TABLE):
        return None
    return MigrationContext.configure(conn).get_current_revision()


def _lock(conn: Connection) -> None:
    """Serialise schema changes: SQLite already holds the write lock; PostgreSQL takes an advisory lock."""
    if conn.dialect.name == "postgresql":
        conn.execute(text("SELECT pg_advisory_xact_lock(hashtext('mapserver-migrate:' || current_schema()))"))


def upgrade(db: Database, revision: str = "head") -> str | None:
    """Upgrade the schema to ``revision`` in one locked transaction; return the new revision.

    Raises:
        StoreError: a migration failed (nothing is changed: the transaction is rolled back).
    """
    try:
        with db.write(check_foreign_keys=False) as conn:
            _lock(conn)
            command.upgrade(alembic_config(conn), revision)
            _check_references(conn)
            return _current(conn)
    except DBAPIError as err:
        msg = f"schema upgrade of {db.display_url()} failed: {' '.join(str(err.orig).split())}"
        raise StoreError(msg) from err


def downgrade(db: Database, revision: str) -> str | None:
    """Downgrade the schema to ``revision`` (``base`` drops everything) in one locked transaction."""
    with db.write(check_foreign_keys=False) as conn:
        _lock(conn)
        command.downgrade(alembic_config(conn), revision)
        _check_references(conn)
        return _current(conn)


def _check_references(conn: Connection) -> None:
    """Refuse (StoreError, rolled back) a migration that left a row referring to a missing one (SQLite).

    SQLite changes a column by copying its table to a new one and dropping the old (Alembic's batch mode); with
    foreign keys enforced, dropping a table deletes every row that refers to it (``ON DELETE CASCADE``): a
    downgrade that dropped ``maps.archived_at`` emptied ``map_states``. Migrations therefore run with
    enforcement off (:meth:`Database.write`), and this checks every reference once they are done.
    """
    if conn.dialect.name != "sqlite":
        return
    broken = conn.exec_driver_sql("PRAGMA foreign_key_check").fetchall()
    if broken:
        tables = sorted({str(row[0]) for row in broken})
        msg = f"the migration left {len(broken)} rows referring to missing rows (tables: {', '.join(tables)})"
        raise StoreError(msg)


def ensure_schema(db: Database, *, upgrade_empty: bool = True) -> None:
    """Check the schema revision; create the schema when the database is empty and ``upgrade_empty``.

    Raises:
        StoreError: the database is unreachable, empty while ``upgrade_empty`` is False, or at a
            revision other than :data:`HEAD_REVISION` (run ``mapserver db upgrade``).
    """
    current = current_revision(db)
    if current == HEAD_REVISION:
        return
    if current is None and upgrade_empty:
        logger.info("creating the map store schema in %s", db.display_url())
        current = upgrade(db)
        if current == HEAD_REVISION:
            return
    if current is None:
        msg = f"{db.display_url()} holds no map store; run: mapserver db upgrade --db URL"
        raise StoreError(msg)
    msg = (
        f"{db.display_url()} is at schema revision {current!r}, this code needs {HEAD_REVISION!r}; "
        "run: mapserver db upgrade --db URL"
    )
    raise StoreError(msg)

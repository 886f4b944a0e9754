"""Database engine and transactions: SQLite by default (WAL, foreign keys, busy timeout), any SQLAlchemy URL.

:func:`open_database` returns a :class:`Database`; every unit of work is one transaction taken from it:

* :meth:`Database.write` — one write transaction. On SQLite it starts with ``BEGIN IMMEDIATE`` (the
  write lock is taken at once, so two writers queue on the busy timeout instead of failing on a lock
  upgrade); on PostgreSQL it is a READ COMMITTED transaction whose first statement on a map row locks it
  (see :func:`mapserver.store.maps.claim_map`).
* :meth:`Database.read` — a consistent snapshot: a deferred SQLite transaction (WAL readers see the
  state as of their first read, never a half-committed write) or a REPEATABLE READ PostgreSQL one.

Both yield a :data:`Connection`, the transaction handle every repository function takes as ``conn``
(SQLAlchemy's ``Connection``; code outside the store names it ``mapserver.store.Connection``).

Driver errors leave as :class:`~mapserver.errors.StoreError` (a lock that outlasted the busy timeout,
a lost connection) or :class:`~mapserver.errors.ConflictError` (a constraint a concurrent writer won).
"""

from __future__ import annotations

import logging
import sqlite3
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import Connection as Connection
from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import URL, make_url
from sqlalchemy.exc import ArgumentError, DBAPIError, IntegrityError

from mapserver.errors import ConflictError, InputError, MapServerError, StoreError

logger = logging.getLogger(__name__)

DEFAULT_DB_URL = "sqlite:///./var/mapserver.db"
"""The contract's default database: a SQLite file under ``./var/`` (created on first use)."""

SQLITE_BUSY_TIMEOUT_S = 60.0
"""How long a SQLite writer waits for another writer's transaction before giving up."""

SQLITE_CACHE_KIB = 65536
"""Page cache per SQLite connection (64 MiB): bulk index inserts of large maps stay in memory."""

SQLITE_STREAM_CACHE_KIB = 1024
"""Page cache of a SQLite connection while it streams a map out (:func:`small_page_cache`)."""

_WRITE_OPTION = "mapserver_write"


def parse_url(url: str | URL | None) -> URL:
    """Return the SQLAlchemy URL for ``url`` (None → :data:`DEFAULT_DB_URL`).

    Raises:
        InputError: the URL cannot be parsed.
    """
    try:
        return make_url(url if url is not None else DEFAULT_DB_URL)
    except (ArgumentError, ValueError) as err:
        msg = f"invalid database URL {str(url)!r}: {err}"
        raise InputError(msg) from err


def _sqlite_file(url: URL) -> Path | None:
    """Return the database file of a SQLite URL (None for in-memory or URI-style databases)."""
    database = url.database
    if not database or database == ":memory:" or database.startswith("file:") or url.query.get("uri"):
        return None
    return Path(database)


def sqlite_database_file(url: str | URL | None) -> Path | None:
    """Return the database file of a SQLite URL (None for other backends, in-memory or URI-style databases).

    Raises:
        InputError: the URL cannot be parsed.
    """
    parsed = parse_url(url)
    return _sqlite_file(parsed) if parsed.get_backend_name() == "sqlite" else None


def create_db_engine(url: str | URL | None = None, **kwargs: Any) -> Engine:
    """Create a SQLAlchemy engine configured for the map store.

    SQLite: the file's directory is created; every connection runs ``PRAGMA foreign_keys=ON``,
    ``journal_mode=WAL``, ``synchronous=NORMAL`` and ``busy_timeout``; transactions are begun by us
    (``BEGIN`` or ``BEGIN IMMEDIATE``), not by the driver. Other databases: ``pool_pre_ping``.

    Args:
        url: any SQLAlchemy URL (None → :data:`DEFAULT_DB_URL`).
        **kwargs: passed to :func:`sqlalchemy.create_engine`.

    Returns:
        The engine.

    Raises:
        InputError: the URL is invalid or names an unknown driver.
        StoreError: the SQLite directory cannot be created.
    """
    parsed = parse_url(url)
    sqlite = parsed.get_backend_name() == "sqlite"
    if sqlite:
        path = _sqlite_file(parsed)
        if path is not None:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as err:
                msg = f"cannot create the database directory {str(path.parent)!r}: {err.strerror or err}"
                raise StoreError(msg) from err
        kwargs.setdefault("connect_args", {}).setdefault("timeout", SQLITE_BUSY_TIMEOUT_S)
    else:
        kwargs.setdefault("pool_pre_ping", True)
    try:
        engine = create_engine(parsed, **kwargs)
    except (ArgumentError, ImportError) as err:
        msg = f"cannot use database URL {parsed.render_as_string(hide_password=True)!r}: {err}"
        raise InputError(msg) from err
    if sqlite:
        _configure_sqlite(engine)
    return engine


def _configure_sqlite(engine: Engine) -> None:
    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection: Any, _record: Any) -> None:
        dbapi_connection.isolation_level = None  # we issue BEGIN ourselves (see _on_begin)
        cursor = dbapi_connection.cursor()
        try:
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.execute(f"PRAGMA busy_timeout={int(SQLITE_BUSY_TIMEOUT_S * 1000)}")
            _switch_to_wal(cursor)
            cursor.execute("PRAGMA synchronous=NORMAL")
            cursor.execute(f"PRAGMA cache_size=-{SQLITE_CACHE_KIB}")
        finally:
            cursor.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn: Connection) -> None:
        write = bool(conn.get_execution_options().get(_WRITE_OPTION))
        conn.exec_driver_sql("BEGIN IMMEDIATE" if write else "BEGIN")


def _switch_to_wal(cursor: Any) -> None:
    """Run ``PRAGMA journal_mode=WAL``, retrying while another connection holds the file exclusively.

    SQLite answers "database is locked" at once, without calling the busy handler, when a connection
    opens the file while another one switches a new file to WAL, recovers a WAL or cleans up after
    its last connection closed (sqlite.org/wal.html, "Sometimes Queries Return SQLITE_BUSY"): two
    processes opening a fresh store together hit it. Retried with backoff up to the busy timeout.
    """
    deadline = time.monotonic() + SQLITE_BUSY_TIMEOUT_S
    delay = 0.001
    while True:
        try:
            cursor.execute("PRAGMA journal_mode=WAL")
            return
        except sqlite3.OperationalError as err:
            if "locked" not in str(err) or time.monotonic() >= deadline:
                raise
        time.sleep(delay)
        delay = min(2 * delay, 0.05)


@contextmanager
def small_page_cache(conn: Connection) -> Iterator[None]:
    """Keep a SQLite connection's page cache at ``SQLITE_STREAM_CACHE_KIB`` for a long sequential read.

    A pooled connection keeps the pages it read (up to ``SQLITE_CACHE_KIB``) for as long as it lives: a
    read of a whole map's rows by each of several connections would leave the server that much larger
    for good. The cache is set back to its size afterwards (it then holds only what the read left, at most
    the small size). Other databases: nothing.
    """
    if conn.dialect.name != "sqlite":
        yield
        return
    conn.exec_driver_sql(f"PRAGMA cache_size=-{SQLITE_STREAM_CACHE_KIB}")
    try:
        yield
    finally:
        conn.exec_driver_sql(f"PRAGMA cache_size=-{SQLITE_CACHE_KIB}")


def _set_foreign_keys(conn: Connection, *, on: bool) -> None:
    """Switch SQLite foreign-key enforcement on the connection's driver connection (outside a transaction)."""
    driver_connection: Any = conn.connection.driver_connection
    driver_connection.execute(f"PRAGMA foreign_keys={'ON' if on else 'OFF'}")


def _describe(err: BaseException) -> str:
    orig = getattr(err, "orig", None)
    text = " ".join(str(orig if orig is not None else err).split()) or type(err).__name__
    return text if len(text) <= 300 else text[:297] + "..."


class Database:
    """A map-store database: an engine plus transaction helpers (a context manager that disposes it).

    Args:
        engine: the SQLAlchemy engine (see :func:`create_db_engine`).
    """

    def __init__(self, engine: Engine) -> None:
        self.engine = engine

    @property
    def url(self) -> URL:
        """Return the engine's URL."""
        return self.engine.url

    @property
    def dialect(self) -> str:
        """Return the backend name: ``sqlite``, ``postgresql``, ..."""
        return self.engine.dialect.name

    def display_url(self) -> str:
        """Return the URL with any password hidden."""
        return self.engine.url.render_as_string(hide_password=True)

    @contextmanager
    def write(self, *, check_foreign_keys: bool = True) -> Iterator[Connection]:
        """Yield a connection inside one write transaction, committed on success, rolled back on error.

        Args:
            check_foreign_keys: False skips SQLite's per-row foreign-key lookups for this transaction
                (they cost a third of a bulk map write). Only for writes whose rows are validated
                before they are inserted — :func:`~mapserver.store.state.write_map_state` checks every
                reference of the snapshot (template, experience and session ids) in bulk. Other
                backends always check.

        Raises:
            StoreError: the database failed (locked past the busy timeout, connection lost, ...).
            ConflictError: a uniqueness or foreign-key constraint was violated (a concurrent writer won).
        """
        with self._translate(), self.engine.connect() as conn:
            relaxed = self.dialect == "sqlite" and not check_foreign_keys
            if self.dialect == "sqlite":
                conn.execution_options(**{_WRITE_OPTION: True})
            if relaxed:  # a no-op inside a transaction: set before BEGIN, restored after COMMIT/ROLLBACK
                _set_foreign_keys(conn, on=False)
            try:
                with conn.begin():
                    yield conn
            finally:
                if relaxed:
                    try:
                        _set_foreign_keys(conn, on=True)
                    except Exception:
                        conn.invalidate()  # never hand a connection without foreign keys back to the pool
                        raise

    @contextmanager
    def read(self) -> Iterator[Connection]:
        """Yield a connection inside one read transaction that sees a single consistent snapshot.

        Raises:
            StoreError: the database failed.
        """
        with self._translate(), self.engine.connect() as conn:
            if self.dialect == "postgresql":
                conn.execution_options(isolation_level="REPEATABLE READ")
            with conn.begin():
                yield conn

    @contextmanager
    def _translate(self) -> Iterator[None]:
        try:
            yield
        except MapServerError:
            raise
        except IntegrityError as err:  # the constraint's text goes to the log, not into answers or job records
            logger.warning("the database refused a conflicting write: %s", _describe(err))
            msg = "another writer stored the same record at the same time; nothing was written (try again)"
            raise ConflictError(msg) from err
        except DBAPIError as err:
            msg = f"database error on {self.display_url()}: {_describe(err)}"
            raise StoreError(msg) from err

    def dispose(self) -> None:
        """Close every pooled connection."""
        self.engine.dispose()

    def __enter__(self) -> Database:
        return self

    def __exit__(self, *exc: object) -> None:
        self.dispose()


def open_database(url: str | URL | None = None, *, upgrade: bool = True, **kwargs: Any) -> Database:
    """Open the map store at ``url``; with ``upgrade``, an empty database gets the schema first.

    A database at an older schema revision is not upgraded silently: that is ``mapserver db upgrade``'s
    job, and the error says so.

    Args:
        url: any SQLAlchemy URL (None → :data:`DEFAULT_DB_URL`).
        upgrade: create the schema when the database is empty (the CLI and the server do).
        **kwargs: passed to :func:`sqlalchemy.create_engine`.

    Returns:
        The database (dispose it, or use it as a context manager).

    Raises:
        InputError: invalid URL.
        StoreError: unreachable database or a schema revision other than the code's.
    """
    from mapserver.store.migrate import ensure_schema  # migrate imports this module

    db = Database(create_db_engine(url, **kwargs))
    try:
        ensure_schema(db, upgrade_empty=upgrade)
    except BaseException:
        db.dispose()
        raise
    return db


_GATES: dict[str, threading.RLock] = {}
_GATES_GUARD = threading.Lock()


def commit_gate(db: Any) -> threading.RLock:
    """Return this process's commit gate of ``db``'s database (one re-entrant lock per URL).

    Every session commit of this process passes the gate; the last of
    ``mapserver.processing.pipeline.STALE_ATTEMPTS`` runs
    of a session holds it from start to commit, so sessions committed by other threads (the embedded job
    engine's workers, parallel ``process`` calls in one program) cannot make it stale and a long
    session is not starved by a stream of short ones. Writers in other processes are not held back.
    """
    key = db.url.render_as_string(hide_password=False)
    with _GATES_GUARD:
        return _GATES.setdefault(key, threading.RLock())

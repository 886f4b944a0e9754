"""Bulk row I/O for the hot paths (map states of 10⁵ experiences): no per-row ORM objects.

:func:`fetch_tuples` runs a SELECT on the driver cursor and returns plain tuples (SQLAlchemy
``Row`` objects are slow to turn into numpy arrays); :func:`iter_tuples` yields them a batch at a time.
:func:`bulk_insert` uses the driver's ``executemany`` on SQLite, ``COPY … FROM STDIN`` on PostgreSQL
with psycopg 3, and SQLAlchemy Core ``executemany`` anywhere else. Every call runs on the caller's
connection, inside its transaction.
"""

from __future__ import annotations

import secrets
from collections.abc import Iterator, Sequence
from typing import Any

from sqlalchemy import ClauseElement, Connection, Table


def bulk_insert(conn: Connection, table: Table, columns: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """Insert ``rows`` (tuples in ``columns`` order) into ``table`` in one round of driver calls."""
    if not rows:
        return
    dialect = conn.dialect
    quote = dialect.identifier_preparer.quote
    names = ", ".join(quote(c) for c in columns)
    if dialect.name == "sqlite":
        marks = ", ".join("?" * len(columns))
        conn.exec_driver_sql(f"INSERT INTO {quote(table.name)} ({names}) VALUES ({marks})", list(rows))
        return
    if dialect.name == "postgresql" and dialect.driver == "psycopg":
        driver_connection: Any = conn.connection.driver_connection
        statement = f"COPY {quote(table.name)} ({names}) FROM STDIN"
        with driver_connection.cursor() as cursor, cursor.copy(statement) as copy:
            for row in rows:
                copy.write_row(row)
        return
    conn.execute(table.insert(), [dict(zip(columns, row, strict=True)) for row in rows])


def fetch_tuples(conn: Connection, statement: ClauseElement) -> list[tuple[Any, ...]]:
    """Run ``statement`` (bound values rendered inline; use it for integers and literals we control only)."""
    compiled = statement.compile(dialect=conn.dialect, compile_kwargs={"literal_binds": True})
    driver_connection: Any = conn.connection.driver_connection
    cursor = driver_connection.cursor()
    try:
        cursor.execute(str(compiled))
        return [tuple(row) for row in cursor.fetchall()] if conn.dialect.name != "sqlite" else cursor.fetchall()
    finally:
        cursor.close()


def iter_tuples(conn: Connection, statement: ClauseElement, batch: int) -> Iterator[list[tuple[Any, ...]]]:
    """Run ``statement`` and yield its rows ``batch`` at a time, never holding more than one batch.

    PostgreSQL with psycopg 3 reads through a server-side (named) cursor inside the caller's transaction;
    SQLite's cursor steps through the result as it is fetched. Bound values are rendered inline, as in
    :func:`fetch_tuples`. Close the generator (or exhaust it) before the transaction ends.
    """
    compiled = statement.compile(dialect=conn.dialect, compile_kwargs={"literal_binds": True})
    driver_connection: Any = conn.connection.driver_connection
    dialect = conn.dialect
    if dialect.name == "postgresql" and dialect.driver == "psycopg":
        cursor = driver_connection.cursor(name=f"mapserver_rows_{secrets.token_hex(6)}")
    else:
        cursor = driver_connection.cursor()
    try:
        cursor.execute(str(compiled))
        while rows := cursor.fetchmany(batch):
            yield rows if isinstance(rows, list) else list(rows)
    finally:
        cursor.close()

"""Alembic environment of the map store.

The database URL comes, in this order, from the connection handed over programmatically
(``config.attributes["connection"]``, as :mod:`mapserver.store.migrate` does), ``alembic -x db=URL``,
the ``MAPSERVER_DB`` environment variable, ``sqlalchemy.url`` in ``alembic.ini``, or the default
``sqlite:///./var/mapserver.db``. The target metadata is :mod:`mapserver.store.models`.
"""

from __future__ import annotations

import os

from alembic import context

from mapserver.store.db import DEFAULT_DB_URL, create_db_engine
from mapserver.store.models import Base

config = context.config
target_metadata = Base.metadata


def _configure(connection) -> None:
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        compare_type=True,
        render_as_batch=connection.dialect.name == "sqlite",
    )


def _url() -> str:
    return (
        context.get_x_argument(as_dictionary=True).get("db")
        or os.environ.get("MAPSERVER_DB")
        or config.get_main_option("sqlalchemy.url")
        or DEFAULT_DB_URL
    )


def run_migrations_offline() -> None:
    context.configure(url=_url(), target_metadata=target_metadata, literal_binds=True, compare_type=True)
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:
        _configure(connection)
        with context.begin_transaction():
            context.run_migrations()
        return
    engine = create_db_engine(_url())
    try:
        with engine.connect() as conn:
            _configure(conn)
            with context.begin_transaction():
                context.run_migrations()
    finally:
        engine.dispose()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()

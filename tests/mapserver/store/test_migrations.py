"""Only migrations build the schema: upgrade/downgrade cycles, models == migrations, first use of a database."""

from __future__ import annotations

import re
import sqlite3
from pathlib import Path

import pytest
import sqlalchemy as sa
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext

from mapserver.cli import main
from mapserver.errors import StoreError
from mapserver.store import (
    HEAD_REVISION,
    Database,
    create_db_engine,
    current_revision,
    downgrade,
    open_database,
    upgrade,
)
from mapserver.store.migrate import MIGRATIONS_DIR, script_head
from mapserver.store.models import Base

TABLES = set(Base.metadata.tables)


def _tables(db: Database) -> set[str]:
    with db.read() as conn:
        return set(sa.inspect(conn).get_table_names()) - {"alembic_version"}


def test_upgrade_downgrade_upgrade_on_an_empty_database(db_url: str) -> None:
    with Database(create_db_engine(db_url)) as db:
        assert current_revision(db) is None
        assert _tables(db) == set()
        assert upgrade(db) == HEAD_REVISION
        assert _tables(db) == TABLES
        assert downgrade(db, "base") is None
        assert _tables(db) == set()
        assert upgrade(db) == HEAD_REVISION
        assert _tables(db) == TABLES
        assert upgrade(db) == HEAD_REVISION  # idempotent


def test_models_match_the_migrations(db: Database) -> None:
    with db.read() as conn:
        context = MigrationContext.configure(conn, opts={"compare_type": True})
        diff = compare_metadata(context, Base.metadata)
    assert diff == []


def test_the_code_expects_the_head_revision_and_files_are_named_rev_slug() -> None:
    assert script_head() == HEAD_REVISION
    files = sorted(p.name for p in (MIGRATIONS_DIR / "versions").glob("*.py"))
    assert files
    for name in files:
        rev, slug = re.fullmatch(r"([0-9a-f]+)_([a-z0-9_]+)\.py", name).groups()  # type: ignore[union-attr]
        text = (MIGRATIONS_DIR / "versions" / name).read_text(encoding="utf-8")
        assert f'revision = "{rev}"' in text, name
        assert slug


def test_first_use_creates_var_and_the_schema_with_wal_and_foreign_keys(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    with open_database(None) as db:  # the contract's default sqlite:///./var/mapserver.db
        assert current_revision(db) == HEAD_REVISION
        with db.read() as conn:
            assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar_one() == 1
            assert conn.exec_driver_sql("PRAGMA journal_mode").scalar_one() == "wal"
            assert conn.exec_driver_sql("PRAGMA busy_timeout").scalar_one() == 60000
    assert (tmp_path / "var" / "mapserver.db").is_file()


def test_a_database_at_another_revision_is_refused(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'old.db'}"
    open_database(url).dispose()
    with sqlite3.connect(tmp_path / "old.db") as raw:
        raw.execute("UPDATE alembic_version SET version_num = '0000'")
    with pytest.raises(StoreError, match="db upgrade"):
        open_database(url)


def test_cli_db_upgrade_and_current(db_url: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["db", "current", "--db", db_url, "--json"]) == 0
    assert '"revision": null' in capsys.readouterr().out
    assert main(["db", "upgrade", "--db", db_url, "--json"]) == 0
    out = capsys.readouterr().out.strip().splitlines()[-1]
    assert f'"revision": "{HEAD_REVISION}"' in out
    assert '"from": null' in out

"""Store test fixtures: a database per test on SQLite (tmp_path) and on PostgreSQL (a schema per test).

PostgreSQL tests use ``postgresql+psycopg://postgres@127.0.0.1:5432/test`` (override with
``MAPSERVER_TEST_PG``); each test gets its own schema (search_path set in the URL), dropped afterwards,
so parallel xdist workers never collide. They are skipped, with the reason, only when the server
cannot be reached.
"""

from __future__ import annotations

import hashlib
import math
import os
import uuid
from collections.abc import Iterator, Mapping
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import sqlalchemy as sa

from core import Engine, Params, preset
from mapserver.ingest.writer import OdomSample, write_log
from mapserver.store import Database, open_database
from mapserver.store.models import Base
from tests.worlds import StripWorld

PG_BASE = os.environ.get("MAPSERVER_TEST_PG", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
T0_NS = 1_700_000_000_000_000_000


@cache
def pg_unreachable() -> str | None:
    """Return why PostgreSQL cannot be used, or None when it can."""
    try:
        engine = sa.create_engine(PG_BASE, connect_args={"connect_timeout": 3})
        with engine.connect() as conn:
            conn.execute(sa.text("SELECT 1"))
        engine.dispose()
    except Exception as err:  # any driver or network failure means "unreachable"
        return f"PostgreSQL unreachable at {PG_BASE}: {' '.join(str(err).split())[:200]}"
    return None


def _pg_schema_url() -> tuple[str, str]:
    schema = f"t_{uuid.uuid4().hex[:16]}"
    engine = sa.create_engine(PG_BASE)
    with engine.begin() as conn:
        conn.execute(sa.text(f'CREATE SCHEMA "{schema}"'))
    engine.dispose()
    return f"{PG_BASE}?options=-csearch_path%3D{schema}", schema


def _pg_drop(schema: str) -> None:
    engine = sa.create_engine(PG_BASE)
    with engine.begin() as conn:
        conn.execute(sa.text(f'DROP SCHEMA IF EXISTS "{schema}" CASCADE'))
    engine.dispose()


BACKENDS = [
    pytest.param("sqlite", id="sqlite"),
    pytest.param("postgresql", id="postgresql", marks=pytest.mark.postgres),
]


@pytest.fixture(params=BACKENDS)
def db_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """An empty database URL: a SQLite file in tmp_path, or a fresh PostgreSQL schema."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'store.db'}"
        return
    reason = pg_unreachable()
    if reason is not None:
        pytest.skip(reason)
    url, schema = _pg_schema_url()
    try:
        yield url
    finally:
        _pg_drop(schema)


@pytest.fixture
def make_url(tmp_path: Path, db_url: str) -> Iterator[Any]:
    """Factory of further empty databases on the same backend as ``db_url``."""
    schemas: list[str] = []

    def factory() -> str:
        if db_url.startswith("sqlite"):
            return f"sqlite:///{tmp_path / f'extra-{uuid.uuid4().hex[:8]}.db'}"
        url, schema = _pg_schema_url()
        schemas.append(schema)
        return url

    yield factory
    for schema in schemas:
        _pg_drop(schema)


@pytest.fixture
def db(db_url: str) -> Iterator[Database]:
    """The map store at ``db_url`` with its schema (built by the migrations)."""
    database = open_database(db_url)
    try:
        yield database
    finally:
        database.dispose()


def row_counts(db: Database) -> dict[str, int]:
    """Return the row count of every table of the schema."""
    with db.read() as conn:
        return {
            name: int(conn.execute(sa.select(sa.func.count()).select_from(table)).scalar_one())
            for name, table in Base.metadata.tables.items()
        }


def small_params() -> Params:
    """Fast parameters: the iRat lattice (11 × 11 × 36) and 60 × 20 templates."""
    return preset("irat")


def drive_engine(params: Params, laps: float = 2.2, seed: int = 3, origin: int = 0) -> Engine:
    """Run an engine around the strip world (loop closures on the second lap)."""
    engine = Engine(params, origin=origin)
    for image, motion, stamp in StripWorld(seed=seed).drive(laps):
        engine.step(image, motion, stamp)
    return engine


def assert_same_arrays(
    expected: Mapping[str, np.ndarray], actual: Mapping[str, np.ndarray], *, skip: tuple[str, ...] = ()
) -> None:
    """Assert the same keys in the same order, and for each the same dtype, shape and bytes."""
    assert list(actual) == list(expected)
    for key, value in expected.items():
        if key in skip:
            continue
        got = actual[key]
        assert got.dtype == value.dtype, key
        assert got.shape == value.shape, key
        assert got.tobytes() == value.tobytes(), key


def digest(snapshot: Mapping[str, np.ndarray]) -> str:
    """Return a SHA-256 over every key, dtype, shape and byte of a snapshot."""
    h = hashlib.sha256()
    for key, value in snapshot.items():
        array = np.ascontiguousarray(value)
        h.update(f"{key}|{array.dtype.str}|{array.shape}".encode())
        h.update(array.tobytes())
    return h.hexdigest()


def write_loop_log(path: Path, *, laps: float = 1.6, seed: int = 3, rate_hz: float = 2.0, speed: float = 1.0) -> Path:
    """Write a ROS 1 bag of the strip world driven around its circle: images at ``rate_hz``, odometry at 10 Hz."""
    world = StripWorld(seed=seed)
    radius = world.perimeter / (2 * math.pi)
    wz = speed / radius
    duration = laps * world.perimeter / speed
    count = int(duration * rate_hz)
    images = [(T0_NS + round(i / rate_hz * 1e9), world.view(speed * i / rate_hz)) for i in range(count)]
    odometry = []
    for j in range(int(duration * 10) + 2):
        t = j / 10
        yaw = wz * t
        odometry.append(
            OdomSample(
                T0_NS + round(t * 1e9), radius * math.sin(yaw), radius * (1 - math.cos(yaw)), 0.0, yaw, speed, 0.0,
                0.0, wz,
            )
        )  # fmt: skip
    return write_log(path, "bag", images, odometry)

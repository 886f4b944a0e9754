"""Streamed exports: the same bytes as the formatters of a loaded map, a batch of rows at a time.

Maps with one and two sessions, the ``odometry`` extension, ``-0.0`` in every patched float row key,
switched-off links of every kind, a planar (SE2) and a 4-DoF (SE3) lattice, an empty map; batches of
7 rows (many batch edges) and the default. Both backends (SQLite; PostgreSQL through a server-side cursor).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from core import Engine, preset
from mapserver.errors import ConflictError, InputError
from mapserver.formats import write_map_json, write_tum
from mapserver.formats.csv import experiences_csv, links_csv
from mapserver.formats.g2o import g2o_text
from mapserver.store import Database, NewSession, load_map, save_map
from mapserver.store.errors import UnknownMapError
from mapserver.store.export import is_planar, map_document, tum_rows
from mapserver.store.sessions import get_reckoning
from mapserver.store.streams import STREAM_FORMATS, open_export
from tests.mapserver.store.conftest import drive_engine, small_params


def _synthetic(preset_name: str, experiences: int, links: int, seed: int, sessions: int) -> tuple[object, dict]:
    """Return (params, snapshot) of a map with random poses, -0.0 values and switched-off links of every kind."""
    params = preset(preset_name)
    snap = Engine(params).snapshot()
    rng = np.random.default_rng(seed)
    ty, tx = params.template_y_size, params.template_x_size
    templates = max(1, experiences // 4)
    snap["lv_templates"] = rng.random((templates, ty, tx), dtype=np.float32)
    snap["lv_means"] = snap["lv_templates"].reshape(templates, -1).mean(axis=1, dtype=np.float64)
    snap["lv_origin"] = rng.integers(0, sessions, templates).astype(np.int64)
    snap["lv_current"] = np.asarray(templates - 1 if experiences else -1, dtype=np.int64)
    pose = np.column_stack([rng.normal(0, 50, (experiences, 3)), rng.uniform(-math.pi, math.pi, experiences)])
    pose[::11, 0] = -0.0
    pose[::13, 3] = -0.0
    pose[::17, 2] = 0.0
    stamps = np.sort(rng.uniform(0, 1000, experiences))
    stamps[: min(3, experiences)] = -0.0  # ties with 0.0, sorted stably
    snap["em_pose"] = pose
    snap["em_pc"] = rng.random((experiences, snap["pc_activity"].ndim))
    snap["em_template"] = rng.integers(0, templates, experiences).astype(np.int64)
    snap["em_stamp"] = stamps
    snap["em_origin"] = np.sort(rng.integers(0, sessions, experiences)).astype(np.int64)
    snap["em_link_from"] = rng.integers(0, max(experiences, 1), links).astype(np.int64)
    snap["em_link_to"] = rng.integers(0, max(experiences, 1), links).astype(np.int64)
    transform = rng.normal(0, 2, (links, 4))
    transform[::5, 1] = -0.0
    transform[::7, 3] = -0.0
    snap["em_link_transform"] = transform
    snap["em_link_dt"] = np.where(np.arange(links) % 9 == 0, -0.0, rng.uniform(0, 5, links))
    snap["em_link_distance"] = np.where(np.arange(links) % 10 == 0, -0.0, rng.uniform(0, 5, links))
    snap["em_link_kind"] = (np.arange(links) % 4).astype(np.int8)
    snap["em_link_active"] = np.arange(links) % 6 != 5
    snap["em_current"] = np.asarray(experiences - 1, dtype=np.int64)
    return params, snap


def _store(db: Database, name: str, params: object, snap: dict, sessions: int, reckoning: bool) -> None:
    specs = [
        NewSession(name=f"{name}-s{k}", log_name=f"{name}{k}.bag", log_sha256=f"{name}{k}".ljust(64, "0")[:64],
                   topics={"image": "/cam"}, params=params.to_dict(), frames_processed=10 + k, origin=k,  # type: ignore[attr-defined]
                   reckoning=np.column_stack([np.arange(50.0), np.full(50, -0.0), np.arange(50.0) * 0.5,
                                              np.zeros(50)]) if reckoning else None)
        for k in range(sessions)
    ]  # fmt: skip
    save_map(db, name=name, params=params, snapshot=snap, sessions=specs)


def _expected(db: Database, name: str, fmt: str, tmp_path: Path) -> bytes:
    """The bytes the formatters of the loaded map write (the export before streaming)."""
    content = load_map(db, name=name)
    snapshot = content.snapshot
    if fmt == "json":
        odometry = None
        if len(content.meta.sessions) == 1:
            with db.read() as conn:
                rows, _pose = get_reckoning(conn=conn, session_id=content.meta.sessions[0].id)
            odometry = rows if rows.shape[0] else None
        write_map_json(tmp_path / "x.json", map_document(content, odometry=odometry))
        return (tmp_path / "x.json").read_bytes()
    if fmt == "tum":
        write_tum(tmp_path / "x.tum", *tum_rows(snapshot))
        return (tmp_path / "x.tum").read_bytes()
    if fmt == "csv":
        return experiences_csv(snapshot, content.meta.session_names()).encode("utf-8")
    if fmt == "links.csv":
        return links_csv(snapshot).encode("utf-8")
    return g2o_text(snapshot, planar=is_planar(content.params)).encode("utf-8")


def _streamed(db: Database, name: str, fmt: str, batch: int) -> bytes:
    stream = open_export(db, name=name, fmt=fmt, batch=batch)
    try:
        return b"".join(stream)
    finally:
        stream.close()


@pytest.mark.parametrize("preset_name", ["irat", "poseidon-lvc"])
def test_streamed_exports_are_the_loaded_maps_bytes(db: Database, tmp_path: Path, preset_name: str) -> None:
    maps = {"one": (1, True, 203, 411), "two": (2, False, 160, 333), "empty": (1, True, 0, 0)}
    for k, (name, (sessions, reckoning, experiences, links)) in enumerate(maps.items()):
        params, snap = _synthetic(preset_name, experiences, links, seed=k, sessions=sessions)
        _store(db, name, params, snap, sessions, reckoning)
    for name in maps:
        for fmt in STREAM_FORMATS:
            expected = _expected(db, name, fmt, tmp_path)
            assert _streamed(db, name, fmt, 7) == expected, (name, fmt)
            assert _streamed(db, name, fmt, 1000) == expected, (name, fmt)
    assert b'"odometry":[' in _streamed(db, "one", "json", 7) and b"-0.0" in _streamed(db, "one", "json", 7)
    assert b"# inactive EDGE_" in _streamed(db, "two", "g2o", 7)


def test_a_driven_map_streams_as_it_exports(db: Database, tmp_path: Path) -> None:
    params = small_params()
    engine = drive_engine(params, laps=2.2, seed=3)
    save_map(db, name="driven", params=params, snapshot=engine.snapshot(), sessions=[
        NewSession(name="monday", log_name="monday.bag", log_sha256="a" * 64, topics={}, params=params.to_dict(),
                   frames_processed=engine.frames)])  # fmt: skip
    for fmt in STREAM_FORMATS:
        assert _streamed(db, "driven", fmt, 50) == _expected(db, "driven", fmt, tmp_path), fmt


def test_refusals_come_before_the_first_chunk(db: Database) -> None:
    params, snap = _synthetic("irat", 20, 30, seed=5, sessions=1)
    snap["em_link_dt"][4] = math.inf
    _store(db, "inf", params, snap, 1, False)
    with pytest.raises(ConflictError, match="non-finite"):
        open_export(db, name="inf", fmt="json")
    assert b" inf" not in _streamed(db, "inf", "tum", 7) and b"inf" in _streamed(db, "inf", "links.csv", 7)
    with pytest.raises(UnknownMapError):
        open_export(db, name="nope", fmt="tum")
    with pytest.raises(InputError, match="unknown export format"):
        open_export(db, name="inf", fmt="xml")


def test_a_closed_stream_ends_its_read(db: Database) -> None:
    params, snap = _synthetic("irat", 500, 800, seed=6, sessions=1)
    _store(db, "big", params, snap, 1, False)
    stream = open_export(db, name="big", fmt="json", batch=10)
    first = next(stream)
    assert first.startswith(b'{"format":"mapserver-map/1"')
    stream.close()
    stream.close()  # idempotent
    with pytest.raises(StopIteration):
        next(stream)
    with db.write() as conn:  # nothing held: a writer gets the database at once
        conn.exec_driver_sql("DELETE FROM links")

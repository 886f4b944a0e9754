"""Map state I/O: load(save(s)) == s array for array, bit for bit; identities; versions; ownership."""

from __future__ import annotations

import json
import math
import uuid

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core import Engine
from mapserver.errors import StoreError
from mapserver.store import (
    Database,
    NewSession,
    OwnershipError,
    StaleMapError,
    UnknownMapError,
    list_maps,
    load_map,
    save_map,
)
from mapserver.store.health import map_health
from tests.mapserver.store.conftest import assert_same_arrays, drive_engine, row_counts, small_params


def _session(name: str = "s", origin: int = 0, sha: str | None = None) -> NewSession:
    params = small_params()
    return NewSession(
        name=name,
        log_name=f"{name}.bag",
        log_sha256=sha or uuid.uuid4().hex * 2,
        topics={"image": "/cam"},
        params=params.to_dict(),
        frames_processed=10,
        origin=origin,
    )


@pytest.fixture(scope="module")
def engine() -> Engine:
    return drive_engine(small_params())


def test_engine_snapshot_round_trip_is_exact(db: Database, engine: Engine) -> None:
    snap = engine.snapshot()
    assert engine.loop_closures > 0 and snap["em_link_kind"].max() == 1  # the map has loop links
    written = save_map(db, name="lab", params=engine.params, snapshot=snap, sessions=[_session()])
    content = load_map(db, name="lab")
    session_id = content.meta.sessions[0].id
    assert_same_arrays(snap, content.snapshot, skip=("lv_origin", "em_origin"))
    assert np.array_equal(content.snapshot["lv_origin"], np.full_like(snap["lv_origin"], session_id))
    assert np.array_equal(content.snapshot["em_origin"], np.full_like(snap["em_origin"], session_id))
    assert content.params == small_params().to_dict()
    assert content.meta.map.version == written.version == 1
    assert np.array_equal(content.meta.template_index, np.arange(engine.template_count))
    assert np.array_equal(content.meta.experience_index, np.arange(engine.experience_count))
    # the restored engine is the same engine: one more frame gives the same state
    restored = Engine.restore(engine.params, content.snapshot, origin=session_id)
    image = np.full((24, 64), 90, dtype=np.uint8)
    original = Engine.restore(engine.params, snap, origin=0)
    a, b = original.step(image, None, 200.0), restored.step(image, None, 200.0)
    assert (a.template, a.action, a.experience) == (b.template, b.action, b.experience)
    assert_same_arrays(original.snapshot(), restored.snapshot(), skip=("lv_origin", "em_origin"))


def test_templates_alone_read_as_in_the_whole_state(db: Database, engine: Engine) -> None:
    """``read_map_templates`` (the stale check's relevance test reads only these) equals the state's lv_templates."""
    from mapserver.store.state import read_map_templates

    written = save_map(db, name="lab", params=engine.params, snapshot=engine.snapshot(), sessions=[_session()])
    with db.read() as conn:
        templates = read_map_templates(conn=conn, map_id=written.map_id)
    assert templates.shape[0] == engine.template_count > 1
    assert np.array_equal(templates, engine.snapshot()["lv_templates"])


def test_saving_a_loaded_map_again_is_the_identity(db: Database, engine: Engine) -> None:
    save_map(db, name="lab", params=engine.params, snapshot=engine.snapshot(), sessions=[_session()])
    first = load_map(db, name="lab")
    ids = [s.id for s in first.meta.sessions]
    save_map(db, name="lab", params=first.params, snapshot=first.snapshot, sessions=ids, expected_version=1)
    second = load_map(db, name="lab")
    assert_same_arrays(first.snapshot, second.snapshot)
    assert second.meta.map.version == 2
    assert np.array_equal(first.meta.template_index, second.meta.template_index)


def test_signed_zeros_infinities_and_unknown_keys_survive(db: Database, engine: Engine) -> None:
    snap = engine.snapshot()
    snap["em_pose"][0, :] = [-0.0, 0.0, -0.0, -0.0]
    snap["lv_means"][1] = -0.0
    snap["em_link_transform"][0, 2] = -0.0
    snap["pc_link_decay"][0] = np.inf
    snap["zz_future_key"] = np.arange(24, dtype=np.int16).reshape(2, 3, 4)
    snap["zz_flag"] = np.asarray(True)
    snap["zz_nan_allowed_here"] = np.array([np.nan, -0.0, 1.5], dtype=np.float32)
    snap["zz_empty"] = np.zeros((0, 7), dtype=np.uint8)
    save_map(db, name="edge", params=engine.params, snapshot=snap, sessions=[_session()])
    loaded = load_map(db, name="edge").snapshot
    assert_same_arrays(snap, loaded, skip=("lv_origin", "em_origin"))
    assert np.signbit(loaded["em_pose"][0, [0, 2, 3]]).all() and not np.signbit(loaded["em_pose"][0, 1])
    assert np.signbit(loaded["lv_means"][1])


def test_an_infinite_link_transform_is_stored_with_a_health_figure_json_can_carry(db: Database, engine: Engine) -> None:
    """The store keeps infinities bit for bit; the map's health leaves that link out (``unmeasured``) instead of
    writing ``Infinity``, which PostgreSQL's JSON refused (the map was not saved there) and SQLite stored."""
    snap = engine.snapshot()
    clean = map_health(engine.params, snap)
    assert clean["links"] >= 2 and clean["unmeasured"] == 0 and clean["residual"] > 0.0
    snap["em_link_transform"][1, 0] = np.inf
    save_map(db, name="inf", params=engine.params, snapshot=snap, sessions=[_session()])
    assert_same_arrays(snap, load_map(db, name="inf").snapshot, skip=("lv_origin", "em_origin"))
    with db.read() as conn:
        (stored,) = [m.health for m in list_maps(conn=conn) if m.name == "inf"]
    assert stored["unmeasured"] == 1 and stored["links"] == clean["links"]
    assert math.isfinite(stored["residual"]) and math.isfinite(stored["worst"])
    assert json.loads(json.dumps(stored, allow_nan=False)) == stored


def test_nan_in_a_row_table_is_refused_and_nothing_is_written(db: Database, engine: Engine) -> None:
    snap = engine.snapshot()
    snap["em_pose"][3, 1] = np.nan
    before = row_counts(db)
    with pytest.raises(StoreError, match=r"em_pose.*NaN \(row 3\)"):
        save_map(db, name="bad", params=engine.params, snapshot=snap, sessions=[_session()])
    assert row_counts(db) == before
    with pytest.raises(UnknownMapError):
        load_map(db, name="bad")


def test_merge_levers_round_trip_and_are_fitted_to_the_experiences_as_the_engine_reads_them(
    db: Database, engine: Engine
) -> None:
    """``em_pc_lever`` (one per experience, the merge's lattice lever arms) is stored exactly; levers of another
    length (an importer's snapshot started from an empty engine's) are stored as ``ExperienceMap.restore`` reads
    them: experiences past the end have lever 0, levers past the last experience are dropped. A lever that is NaN
    or negative is refused, and nothing is written."""
    snap = engine.snapshot()
    n = snap["em_pose"].shape[0]
    snap["em_pc_lever"] = np.linspace(0.5, 7.5, n)
    save_map(db, name="levers", params=engine.params, snapshot=snap, sessions=[_session()])
    assert np.array_equal(load_map(db, name="levers").snapshot["em_pc_lever"], snap["em_pc_lever"])
    save_map(db, name="short", params=engine.params, snapshot={**snap, "em_pc_lever": snap["em_pc_lever"][:2]},
             sessions=[_session("short")])  # fmt: skip
    short = load_map(db, name="short").snapshot["em_pc_lever"]
    assert short.tolist() == [0.5, snap["em_pc_lever"][1]] + [0.0] * (n - 2)
    save_map(db, name="long", params=engine.params, snapshot={**snap, "em_pc_lever": np.ones(n + 3)},
             sessions=[_session("long")])  # fmt: skip
    assert load_map(db, name="long").snapshot["em_pc_lever"].tolist() == [1.0] * n
    restored = Engine.restore(engine.params, {**snap, "em_pc_lever": snap["em_pc_lever"][:2]})
    assert np.array_equal(restored.map.lattice_levers, short)
    before = row_counts(db)
    for bad in (np.nan, -1.0):
        wrong = snap["em_pc_lever"].copy()
        wrong[3] = bad
        with pytest.raises(StoreError, match="em_pc_lever"):
            save_map(db, name="bad", params=engine.params, snapshot={**snap, "em_pc_lever": wrong},
                     sessions=[_session("bad")])  # fmt: skip
    assert row_counts(db) == before


def test_a_stale_version_is_refused_and_the_map_is_unchanged(db: Database, engine: Engine) -> None:
    snap = engine.snapshot()
    save_map(db, name="lab", params=engine.params, snapshot=snap, sessions=[_session()])
    stored = load_map(db, name="lab")
    ids = [s.id for s in stored.meta.sessions]
    save_map(db, name="lab", params=engine.params, snapshot=stored.snapshot, sessions=ids, expected_version=1)
    changed = dict(stored.snapshot)
    changed["em_pose"] = changed["em_pose"] + 1.0
    with pytest.raises(StaleMapError, match="version 2, expected 1"):
        save_map(db, name="lab", params=engine.params, snapshot=changed, sessions=ids, expected_version=1)
    assert_same_arrays(stored.snapshot, load_map(db, name="lab").snapshot)


def test_continuing_keeps_identities_and_numbers_new_rows_on(db: Database) -> None:
    params = small_params()
    engine = drive_engine(params, laps=1.0)
    save_map(db, name="lab", params=params, snapshot=engine.snapshot(), sessions=[_session()])
    first = load_map(db, name="lab")
    sid = first.meta.sessions[0].id
    more = Engine.restore(params, first.snapshot, origin=sid)
    for k in range(12):
        more.step(np.roll(np.full((24, 64), 50, dtype=np.uint8), k) + k * 9, None, 500.0 + k)
    assert more.template_count > engine.template_count
    save_map(db, name="lab", params=params, snapshot=more.snapshot(), sessions=[sid], expected_version=1)
    second = load_map(db, name="lab")
    n_old, n_new = engine.template_count, more.template_count
    assert np.array_equal(second.meta.template_index, np.arange(n_new))
    assert np.array_equal(second.meta.template_index[:n_old], first.meta.template_index)
    assert np.array_equal(second.meta.experience_index, np.arange(more.experience_count))


def test_renumbering_moves_template_rows_without_copying_them(db: Database, engine: Engine) -> None:
    snap = engine.snapshot()
    save_map(db, name="lab", params=engine.params, snapshot=snap, sessions=[_session()])
    stored = load_map(db, name="lab")
    n = engine.template_count
    order = np.arange(n)[::-1].copy()  # a merge-like renumbering: template i moves to n-1-i
    moved = dict(stored.snapshot)
    moved["lv_templates"] = stored.snapshot["lv_templates"][order]
    moved["lv_means"] = stored.snapshot["lv_means"][order]
    moved["lv_origin"] = stored.snapshot["lv_origin"][order]
    inverse = np.argsort(order)
    moved["em_template"] = inverse[stored.snapshot["em_template"]]
    moved["pc_link_template"] = inverse[stored.snapshot["pc_link_template"]]
    before = row_counts(db)["templates"]
    save_map(
        db, name="lab", params=engine.params, snapshot=moved, sessions=[stored.meta.sessions[0].id],
        expected_version=1, template_index=stored.meta.template_index[order],
        experience_index=stored.meta.experience_index,
    )  # fmt: skip
    again = load_map(db, name="lab")
    assert row_counts(db)["templates"] == before == n
    assert np.array_equal(again.meta.template_index, stored.meta.template_index[order])
    assert_same_arrays(moved, again.snapshot)


def test_content_of_one_map_cannot_be_saved_into_another(db: Database, engine: Engine) -> None:
    save_map(db, name="a", params=engine.params, snapshot=engine.snapshot(), sessions=[_session("a")])
    a = load_map(db, name="a")
    with pytest.raises(OwnershipError, match="in map id"):
        save_map(db, name="b", params=engine.params, snapshot=a.snapshot, sessions=[a.meta.sessions[0].id])
    with pytest.raises(UnknownMapError):
        load_map(db, name="b")


def test_origins_must_name_sessions_of_the_map(db: Database, engine: Engine) -> None:
    with pytest.raises(StoreError, match=r"origin tag\(s\) \[0\]"):
        save_map(db, name="x", params=engine.params, snapshot=engine.snapshot(), sessions=[_session(origin=7)])


def test_references_are_checked_even_where_sqlite_skips_foreign_keys(db: Database, engine: Engine) -> None:
    # save_map writes without SQLite's per-row foreign-key lookups; its own checks must refuse what they would
    snap = engine.snapshot()
    before = row_counts(db)
    with pytest.raises(StoreError, match=r"session id\(s\) \[987654\] are not stored"):
        save_map(db, name="ghost", params=engine.params, snapshot=snap, sessions=[987654])
    bad = dict(snap)
    bad["em_link_to"] = snap["em_link_to"].copy()
    bad["em_link_to"][0] = len(snap["em_pose"])
    with pytest.raises(StoreError, match=r"em_link_to.*outside"):
        save_map(db, name="dangling", params=engine.params, snapshot=bad, sessions=[_session()])
    assert row_counts(db) == before
    with db.read() as conn:  # the pooled connection has its foreign keys back
        if db.dialect == "sqlite":
            assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1


# --------------------------------------------------------------------------------------- property test

_finite = st.floats(allow_nan=False, width=64)


@st.composite
def snapshots(draw: st.DrawFn) -> dict[str, np.ndarray]:
    """Random small snapshots with the engine's schema (values anywhere, incl. ±0.0, ±inf, subnormals)."""
    rank = draw(st.sampled_from([3, 4]))
    n = draw(st.integers(0, 5))
    e = draw(st.integers(0, 6)) if n else 0
    k = draw(st.integers(0, 6)) if e else 0
    lpc = draw(st.integers(0, 4)) if n else 0
    ty, tx = draw(st.integers(1, 3)), draw(st.integers(1, 4))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)

    def floats(shape: tuple[int, ...], finite: bool = False) -> np.ndarray:
        values = st.floats(allow_nan=False, allow_infinity=False) if finite else _finite
        flat = [draw(values) for _ in range(int(np.prod(shape)))]
        return np.array(flat, dtype=np.float64).reshape(shape)

    shape = (*(3, 4, 2, 5)[: rank - 1], 6)
    return {
        "lv_templates": rng.standard_normal((n, ty, tx)).astype(np.float32),
        "lv_means": floats((n,)),
        "lv_origin": np.zeros(n, dtype=np.int64),
        "lv_current": np.asarray(draw(st.integers(-1, 5)), dtype=np.int64),
        "pc_activity": floats(shape) if draw(st.booleans()) else rng.random(shape),
        "pc_link_template": rng.integers(0, max(n, 1), lpc).astype(np.int64),
        "pc_link_coords": floats((lpc, rank)),
        "pc_link_strength": floats((lpc,)),
        "pc_link_decay": floats((lpc,)),
        "em_pose": floats((e, 4), finite=True),
        "em_pc": floats((e, rank)),
        "em_template": rng.integers(0, max(n, 1), e).astype(np.int64),
        "em_stamp": floats((e,)),
        "em_origin": np.zeros(e, dtype=np.int64),
        "em_link_from": rng.integers(0, max(e, 1), k).astype(np.int64),
        "em_link_to": rng.integers(0, max(e, 1), k).astype(np.int64),
        "em_link_transform": floats((k, 4)),
        "em_link_dt": floats((k,)),
        "em_link_distance": floats((k,)),
        "em_link_kind": rng.integers(0, 4, k).astype(np.int8),
        "eng_last_stamp": np.asarray(draw(st.floats(allow_nan=True)), dtype=np.float64),
        "gate_history": rng.integers(-1, 9, draw(st.integers(0, 4))).astype(np.int64),
        "em_relax_pending": np.asarray(draw(st.booleans())),
    }


@pytest.mark.parametrize("db_url", ["sqlite"], indirect=True)
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(snap=snapshots())
def test_any_snapshot_round_trips_bit_for_bit(db: Database, snap: dict[str, np.ndarray]) -> None:
    name = f"m-{uuid.uuid4().hex[:12]}"
    save_map(db, name=name, params=small_params(), snapshot=snap, sessions=[_session(name)])
    loaded = load_map(db, name=name)
    assert_same_arrays(snap, loaded.snapshot, skip=("lv_origin", "em_origin"))
    sid = loaded.meta.sessions[0].id
    assert set(loaded.snapshot["lv_origin"].tolist()) <= {sid}
    assert set(loaded.snapshot["em_origin"].tolist()) <= {sid}


def test_view_cells_a_merge_reexpressed_are_rewritten_for_sdr_maps_only(db: Database, engine: Engine) -> None:
    """An sdr-htm merge re-expresses a stored session's view cells in another cortex (mapserver.merge.cortex):
    their rows take the new content. Intensity templates stay immutable: the same change is refused."""
    save_map(db, name="lab", params=engine.params, snapshot=engine.snapshot(), sessions=[_session()])
    first = load_map(db, name="lab")
    ids = [s.id for s in first.meta.sessions]
    changed = dict(first.snapshot)
    changed["lv_templates"] = first.snapshot["lv_templates"][::-1].copy()
    changed["lv_means"] = first.snapshot["lv_means"][::-1].copy()
    with pytest.raises(StoreError, match="stored with other data"):
        save_map(db, name="lab", params=engine.params, snapshot=changed, sessions=ids, expected_version=1)
    assert_same_arrays(first.snapshot, load_map(db, name="lab").snapshot)  # nothing written
    sdr = engine.params.replace(frontend="sdr-htm")
    save_map(db, name="lab", params=sdr, snapshot=changed, sessions=ids, expected_version=1)
    again = load_map(db, name="lab")
    assert_same_arrays(changed, again.snapshot)
    assert np.array_equal(again.meta.template_index, first.meta.template_index)  # the same rows, new content

"""Switched-off links (core.robust) in the store, the maps listing, the export and the API health figure."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa

from core import Engine, LinkKind
from core.robust import false_loop_links
from mapserver.cli import main
from mapserver.formats import read_map_json
from mapserver.store import Database, NewSession, load_map, save_map
from mapserver.store.health import map_health
from mapserver.store.models import Link
from tests.mapserver.store.conftest import drive_engine, small_params


def _with_false_links(engine: Engine, count: int) -> np.ndarray:
    """Inject ``count`` wrong loop links (test hook), settle; return the indices of the injected links."""
    src, dst, transform = false_loop_links(engine.map.poses, count, 3.0, seed=1)
    first = engine.map.link_count
    for a, b, t in zip(src.tolist(), dst.tolist(), transform, strict=True):
        assert engine.map.add_link_raw(a, b, t, 1.0, 0.1, LinkKind.LOOP)
    engine.settle()
    return np.arange(first, engine.map.link_count)


def _save(db: Database, engine: Engine, name: str) -> None:
    params = small_params()
    save_map(db, name=name, params=params, snapshot=engine.snapshot(), sessions=[
        NewSession(name=name, log_name=f"{name}.bag", log_sha256=name[0] * 64, topics={}, params=params.to_dict(),
                   frames_processed=engine.frames)])  # fmt: skip


@pytest.fixture(scope="module")
def engines() -> tuple[Engine, Engine, np.ndarray]:
    clean = drive_engine(small_params(), laps=2.2, seed=3)
    clean.settle()
    bad = drive_engine(small_params(), laps=2.2, seed=3)
    injected = _with_false_links(bad, 3)
    return clean, bad, injected


def test_injected_links_are_switched_off_and_true_closures_kept(engines) -> None:  # type: ignore[no-untyped-def]
    clean, bad, injected = engines
    active = bad.map.link_active
    assert not active[injected].any()
    assert active[: clean.map.link_count].all()  # every true link, loop closures included, stays on
    assert int(np.count_nonzero(clean.map.links[5] == LinkKind.LOOP)) > 0
    assert np.abs(bad.map.poses[:, :3] - clean.map.poses[:, :3]).max() < 1e-6


def test_link_status_round_trips_through_the_store(db: Database, engines) -> None:  # type: ignore[no-untyped-def]
    _, bad, injected = engines
    _save(db, bad, "bent")
    snapshot = load_map(db, name="bent").snapshot
    assert np.array_equal(snapshot["em_link_active"], bad.map.link_active)
    differ = [k for k, v in bad.snapshot().items() if not np.array_equal(v, snapshot[k])]
    assert differ == ["lv_origin", "em_origin"]  # origins become the session's id; the rest is exact
    with db.read() as conn:
        off = conn.execute(sa.select(Link.seq).where(Link.active.is_(False)).order_by(Link.seq)).scalars().all()
    assert off == injected.tolist()


def test_maps_json_reports_health(db: Database, db_url: str, engines, capsys) -> None:  # type: ignore[no-untyped-def]
    clean, bad, injected = engines
    _save(db, clean, "clean")
    _save(db, bad, "bent")
    assert main(["maps", "--db", db_url, "--json"]) == 0
    maps = {m["name"]: m for m in json.loads(capsys.readouterr().out.splitlines()[-1])["maps"]}
    assert maps["bent"]["health"]["switched_off"] == injected.size
    assert maps["bent"]["health"]["links"] == bad.map.link_count
    assert maps["clean"]["health"]["switched_off"] == 0
    expected = map_health(small_params(), clean.snapshot())["residual"]
    assert maps["clean"]["health"]["residual"] == pytest.approx(expected)
    # the figure flags a map whose false links still pull: high before, normal after
    kept = dict(bad.snapshot())
    kept["em_link_active"] = np.ones_like(kept["em_link_active"])
    before = Engine.restore(small_params().replace(exp_robust=False), kept)
    before.settle()
    flagged = map_health(small_params(), before.snapshot())
    assert flagged["worst"] > 3.0 and flagged["residual"] > 2 * maps["clean"]["health"]["residual"]
    assert maps["bent"]["health"]["worst"] <= 3.0
    assert maps["bent"]["health"]["residual"] < 1.2 * maps["clean"]["health"]["residual"]


def test_export_json_marks_switched_off_links(db: Database, db_url: str, engines, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    _, bad, injected = engines
    _save(db, bad, "bent")
    out = tmp_path / "map.json"
    assert main(["export", "--db", db_url, "--map", "bent", "--format", "json", "--out", str(out)]) == 0
    links = read_map_json(out)["links"]
    assert [i for i, link in enumerate(links) if link.get("active", True) is False] == injected.tolist()
    assert all("active" not in link for i, link in enumerate(links) if i not in set(injected.tolist()))
    png = tmp_path / "map.png"
    assert main(["export", "--db", db_url, "--map", "bent", "--format", "png", "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

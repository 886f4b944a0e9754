"""``GET /v1/maps/{name}/export``: streamed formats equal the CLI's files; PNGs drawn without a lock; a limit.

Pairs: an export within the limit is answered 200 while one beyond it gets 503 with ``Retry-After``; a slot
is free again once an export ends, whether the client read it to the end or went away in the middle.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from mapserver.cli import main
from mapserver.store import open_database
from mapserver.store.export import read_plot_graph, render_png
from tests.mapserver.api.conftest import Api, Server, bearer, make_token
from tests.mapserver.api.graphmaps import store_graph_map


def _ring(db_url: str, name: str, count: int) -> None:
    angle = np.linspace(0, 2 * np.pi, count, endpoint=False)
    poses = np.column_stack([10 * np.cos(angle), 10 * np.sin(angle), np.zeros(count), angle])
    poses[::7, 2] = -0.0
    store_graph_map(db_url, name, poses, [(k, (k + 1) % count, 1.0, 0.5) for k in range(count)])


@pytest.mark.parametrize(("query", "cli_format", "suffix"), [
    ("format=json", "json", ""), ("format=tum", "tum", ""), ("format=g2o", "g2o", ""), ("format=csv", "csv", ""),
    ("format=csv&table=links", "csv", ".links"),
])  # fmt: skip
def test_rest_exports_are_the_cli_files(api: Api, tmp_path: Path, query: str, cli_format: str, suffix: str) -> None:
    _ring(api.db_url, "ring", 2500)
    response = api.client.get(f"/v1/maps/ring/export?{query}", headers=api.read)
    assert response.status_code == 200, response.text
    out = tmp_path / f"ring.{cli_format}"
    assert main(["export", "--db", api.db_url, "--map", "ring", "--format", cli_format, "--out", str(out)]) == 0
    written = out.with_name(f"ring{suffix}.{cli_format}") if suffix else out
    assert response.content == written.read_bytes()
    assert response.headers["content-disposition"].startswith("inline; filename*=UTF-8''ring")
    assert api.client.app.state.export_slots.running == 0  # type: ignore[attr-defined]


def test_pngs_render_at_once_without_a_lock(api: Api) -> None:
    _ring(api.db_url, "ring", 300)
    with open_database(api.db_url) as db:
        graph = read_plot_graph(db, name="ring")
    alone = render_png(graph)
    results: list[bytes] = []
    threads = [threading.Thread(target=lambda: results.append(render_png(graph))) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert results == [alone] * 4
    response = api.client.get("/v1/maps/ring/export?format=png", headers=api.read)
    assert response.status_code == 200 and response.content[:8] == b"\x89PNG\r\n\x1a\n"


def test_exports_beyond_the_limit_get_503_with_retry_after(make_api: object) -> None:
    api: Api = make_api(max_exports=2)  # type: ignore[operator]
    _ring(api.db_url, "ring", 50)
    slots = api.client.app.state.export_slots  # type: ignore[attr-defined]
    held = [slots.acquire(), slots.acquire()]
    for fmt in ("json", "png"):
        refused = api.client.get(f"/v1/maps/ring/export?format={fmt}", headers=api.read)
        assert refused.status_code == 503
        assert refused.headers["retry-after"] == "2"
        assert "2 exports are running" in refused.json()["detail"]
    assert api.client.get("/v1/maps", headers=api.read).status_code == 200  # other reads go on
    held.pop()()
    assert api.client.get("/v1/maps/ring/export?format=json", headers=api.read).status_code == 200
    assert api.client.get("/v1/maps/ring/export?format=png", headers=api.read).status_code == 200
    assert api.client.get("/v1/maps/nope/export", headers=api.read).status_code == 404
    assert slots.running == 1  # only the slot still held here


def test_a_client_gone_mid_export_frees_its_slot(server: Server) -> None:
    import subprocess

    from tests.mapserver.api.conftest import MAPSERVER

    _ring(server.db_url, "big", 30_000)
    token = make_token(server.db_url, "read")
    server.process = subprocess.Popen(
        [MAPSERVER, "serve", "--db", server.db_url, "--port", str(server.port), "--upload-dir", str(server.upload_dir),
         "--max-exports", "1", "--log-level", "warning"],
        stdout=server.log.open("ab"), stderr=subprocess.STDOUT,
    )  # fmt: skip
    _wait_up(server)
    with httpx.Client(base_url=server.url, headers=bearer(token), timeout=30) as client:
        with client.stream("GET", "/v1/maps/big/export?format=json") as partial:
            assert partial.status_code == 200
            next(partial.iter_raw(65536))  # one chunk, then the client goes away
            refused = client.get("/v1/maps/big/export?format=tum")
            assert refused.status_code == 503
        deadline = time.monotonic() + 20
        while (answer := client.get("/v1/maps/big/export?format=tum")).status_code == 503:
            assert time.monotonic() < deadline, "the slot of the abandoned export was not freed"
            time.sleep(0.1)
        assert answer.status_code == 200 and answer.text.count("\n") == 30_001


def _wait_up(server: Server) -> None:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if httpx.get(server.url + "/healthz", timeout=1).status_code == 200:
                return
        except httpx.HTTPError:
            time.sleep(0.1)
    raise AssertionError(server.log.read_text()[-2000:])

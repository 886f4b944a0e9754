"""The server under hostile input (issue 61): archive and image bombs, bad odometry, damaged logs, bad queries.

Every refusal is a 4xx whose body names its reason (a limit's refusal: 413 and ``limit``), keeps nothing and
queues nothing; each is paired with an ordinary input at the limit that is accepted and processed. The bombs
are measured on a real ``mapserver serve`` process (``/proc/PID/io`` and ``VmHWM``).
"""

from __future__ import annotations

import gzip
import io
import tarfile
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from unittest import mock

import httpx
import pytest
from fastapi.testclient import TestClient

from mapserver.api import archives
from mapserver.api.archives import ArchiveLimits
from mapserver.errors import LimitError, StoreError
from tests.mapserver.api.conftest import Api, Server, free_port, make_token
from tests.mapserver.api.logs import write_strip_log, zip_directory
from tests.mapserver.hostile import (
    bad_odometry_log,
    damaged,
    encoded,
    entries_zip,
    float_columns,
    jpeg_bomb,
    nonfinite_floats,
    payload_bag,
    png_bomb,
    proc_figures,
    zeros_tar,
    zeros_zip,
)
from tests.mapserver.store.conftest import _pg_drop, _pg_schema_url, pg_unreachable

MIB = 1 << 20
NAN = float("nan")


def _kept(api: Api) -> list[Path]:
    return sorted(p for p in api.settings.uploads.rglob("*") if p.is_file())


def _jobs(api: Api) -> int:
    from mapserver.store import open_database
    from mapserver.store.jobs import count_jobs

    with open_database(api.db_url) as db, db.read() as conn:
        return sum(count_jobs(conn=conn).values())


def _wchar() -> int:
    return proc_figures_self()["wchar"]


def proc_figures_self() -> dict[str, int]:
    import os

    return proc_figures(os.getpid())


def _refused(api: Api, path: Path, limit: str | None, status: int = 413, **fields: str) -> dict[str, Any]:
    response = api.upload(path, preset="irat", **fields)
    assert response.status_code == status, response.text
    body = response.json()
    assert body.get("limit") == limit, body
    assert _kept(api) == [] and _jobs(api) == 0
    return body


# ------------------------------------------------------------------------------------------ archive bombs
BOMBS = {
    "tar.bz2": lambda folder: zeros_tar(folder / "zeros.tar.bz2", 256 * MIB, "bz2"),
    "tar.gz": lambda folder: zeros_tar(folder / "zeros.tar.gz", 256 * MIB, "gz"),
    "zip": lambda folder: zeros_zip(folder / "zeros.zip", 128 * MIB),
}


@pytest.mark.parametrize("kind", list(BOMBS))
def test_archive_bombs_stop_at_their_budget_and_name_it(api: Api, tmp_path: Path, kind: str) -> None:
    """A bag directory of zeros (256 MiB tars, 128 MiB zip): 413 naming ``max_unpacked_ratio``; the bytes
    written (this process's ``wchar``) stay under the upload plus 200× its size."""
    bomb = BOMBS[kind](tmp_path)
    size = bomb.stat().st_size
    assert size * 200 < 128 * MIB
    before = _wchar()
    body = _refused(api, bomb, "max_unpacked_ratio")
    written = _wchar() - before
    assert f"the limit is max_unpacked_ratio = 200 × the archive's {size} bytes" in body["detail"]
    assert written <= 2 * size + 200 * size + MIB, written


def test_archive_bytes_over_max_unpacked_bytes_name_that_limit(make_api: Any, tmp_path: Path) -> None:
    api = make_api(max_unpacked_bytes=1_000_000)
    body = _refused(api, zeros_tar(tmp_path / "z.tar.gz", 8 * MIB, "gz"), "max_unpacked_bytes")
    assert body["detail"] == ("archive entry 'bag/zeros.db3' of 8388608 bytes ends past 1000000 bytes; the limit is "
                              "max_unpacked_bytes = 1000000")  # refused from its header, before its data


def test_a_tar_whose_entries_each_fit_is_refused_at_the_entry_that_would_pass_the_budget(
    make_api: Any, tmp_path: Path
) -> None:
    """Every entry is under the budget; the one whose data would end past it (its position in the decompressed
    stream) is refused from its header, so the bytes written stay under the budget."""
    api = make_api(max_unpacked_bytes=10 * MIB, max_unpacked_ratio=1e6)
    archive = tmp_path / "parts.tar.gz"
    with tarfile.open(archive, "w:gz") as tf:
        for k in range(16):
            info = tarfile.TarInfo(f"bag/part{k}.db3")
            info.size = MIB
            tf.addfile(info, io.BytesIO(bytes(MIB)))
    before = _wchar()
    body = _refused(api, archive, "max_unpacked_bytes")
    assert body["detail"].startswith(f"archive entry 'bag/part9.db3' of {MIB} bytes ends past {10 * MIB} bytes")
    assert _wchar() - before <= archive.stat().st_size + 10 * MIB


def test_the_decompressed_stream_is_counted_as_it_is_read() -> None:
    """The backstop under the header checks: a stream read past the budget raises, whoever reads it."""
    budget = archives._Budget(ArchiveLimits(MIB, 1e6, 10), archive_bytes=100)
    counted = archives._Counted(io.BytesIO(bytes(3 * MIB)), budget)
    assert len(counted.read(MIB)) == MIB
    with pytest.raises(LimitError, match=f"archive unpacks to more than {MIB} bytes"):
        counted.read(1)


def test_many_entries_are_refused_before_the_zip_directory_is_read(api: Api, tmp_path: Path) -> None:
    bomb = entries_zip(tmp_path / "entries.zip", 20_000)
    with mock.patch.object(archives.zipfile, "ZipFile", side_effect=AssertionError("read")) as reader:
        body = _refused(api, bomb, "max_archive_entries")
    assert reader.call_count == 0
    assert body["detail"] == "archive has 20000 entries; the limit is max_archive_entries = 1000"


def test_many_tar_entries_are_refused_as_they_come(api: Api, tmp_path: Path) -> None:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz") as tf:
        for k in range(1001):
            tf.addfile(tarfile.TarInfo(f"bag/f{k}"), io.BytesIO(b""))
    archive = tmp_path / "entries.tar.gz"
    archive.write_bytes(buffer.getvalue())
    body = _refused(api, archive, "max_archive_entries")
    assert body["detail"] == "archive has more than 1000 entries; the limit is max_archive_entries = 1000"


def test_an_oversized_tar_header_is_refused_unread(api: Api, tmp_path: Path) -> None:
    info = tarfile.TarInfo("bag/" + "x" * 100)
    info.pax_headers = {"comment": "y" * (2 * MIB)}
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:gz", format=tarfile.PAX_FORMAT) as tf:
        tf.addfile(info, io.BytesIO(b""))
    archive = tmp_path / "header.tar.gz"
    archive.write_bytes(buffer.getvalue())
    body = _refused(api, archive, None, status=400)
    assert "extended tar header" in body["detail"]


def _ordinary(tmp_path: Path, kind: str) -> tuple[Path, int, int]:
    """Return the strip log's bag directory as an archive, its unpacked bytes (as counted) and entries."""
    bag = write_strip_log(tmp_path / "logs" / "rosbag2_strip", fmt="db3", directory=True)
    out = tmp_path / "archives"
    out.mkdir(exist_ok=True)
    if kind == "zip":
        archive = zip_directory(bag, out / "strip.zip")
        with zipfile.ZipFile(archive) as zf:
            return archive, sum(i.file_size for i in zf.infolist()), len(zf.infolist())
    archive = out / "strip.tar.gz"
    with tarfile.open(archive, "w:gz") as tf:
        tf.add(bag, arcname=bag.name)
    with tarfile.open(archive) as tf:
        entries = len(tf.getmembers())
    return archive, len(gzip.decompress(archive.read_bytes())), entries


@pytest.mark.parametrize("kind", ["zip", "tar.gz"])
def test_an_archive_at_every_limit_is_processed_and_one_step_over_each_is_refused(
    make_api: Any, tmp_path: Path, kind: str
) -> None:
    archive, unpacked, entries = _ordinary(tmp_path, kind)
    ratio = unpacked / archive.stat().st_size
    exact = {"max_unpacked_bytes": unpacked, "max_unpacked_ratio": max(ratio + 1e-9, 1.0),
             "max_archive_entries": entries}  # fmt: skip
    api = make_api(**exact)
    response = api.upload(archive, preset="irat")
    assert response.status_code == 202, response.text
    assert api.wait(response.json()["job"])["status"] == "done"
    over = {"max_unpacked_bytes": unpacked - 1, "max_unpacked_ratio": ratio - 0.01, "max_archive_entries": entries - 1}
    if ratio - 0.01 < 1:  # a stored zip unpacks to about its own size: the ratio limit cannot be set below 1
        del over["max_unpacked_ratio"]
    for name, value in over.items():
        tight = make_api(**{**exact, name: value, "upload_dir": tmp_path / f"uploads-{name}",
                            "db_url": f"sqlite:///{tmp_path / f'{name}.db'}"})  # fmt: skip
        _refused(tight, archive, name)


def test_archive_limits_name_the_smaller_budget() -> None:
    limits = ArchiveLimits(max_bytes=8 << 30, max_ratio=200.0, max_entries=1000)
    assert limits.budget(1600)[:2] == (320_000, "max_unpacked_ratio")
    assert limits.budget(1 << 30)[:2] == (8 << 30, "max_unpacked_bytes")


# ------------------------------------------------------------------------------------------ image bombs
@pytest.mark.parametrize("fmt", ["png", "jpeg"])
def test_an_image_bomb_bag_is_413_at_upload(api: Api, tmp_path: Path, fmt: str) -> None:
    payload = png_bomb(20000, 20000) if fmt == "png" else jpeg_bomb(20000, 20000)
    bag = payload_bag(tmp_path / f"{fmt}.bag", [payload] * 3, fmt)
    body = _refused(api, bag, "max_image_pixels")
    assert "20000x20000 = 400000000 pixels, more than the limit max_image_pixels = 33554432" in body["detail"]
    assert str(api.settings.uploads) not in body["detail"]


def test_the_pixel_limit_pairs_and_a_later_bomb_fails_its_job(make_api: Any, tmp_path: Path) -> None:
    """The limit is the process's (the app's lifespan sets it): one app at a time here."""
    log = write_strip_log(tmp_path / "strip.bag")  # 64×20 frames
    at = make_api(max_image_pixels=1280)
    accepted = at.upload(log, preset="irat")
    assert accepted.status_code == 202
    assert at.wait(accepted.json()["job"])["status"] == "done"
    late = payload_bag(tmp_path / "late.bag", [encoded("png", 64, 20, k) for k in range(6)] + [png_bomb(20000, 20000)],
                       "png")  # fmt: skip
    response = at.upload(late, preset="irat")
    assert response.status_code == 202  # the upload check decodes the first frame only
    job = at.wait(response.json()["job"])
    assert job["status"] == "failed" and "max_image_pixels = 1280" in job["error"]
    assert "--" not in job["error"]  # a job's message names the limit's key (GET /v1/limits), never a CLI flag
    at.client.__exit__(None, None, None)
    below = make_api(max_image_pixels=1279, upload_dir=tmp_path / "u2", db_url=f"sqlite:///{tmp_path / 'b.db'}")
    _refused(below, log, "max_image_pixels")


# ------------------------------------------------------------------------------------------ bad odometry
@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def backend_api(request: pytest.FixtureRequest, make_api: Any) -> Iterator[Api]:
    if request.param == "sqlite":
        yield make_api()
        return
    reason = pg_unreachable()
    if reason is not None:
        pytest.skip(reason)
    url, schema = _pg_schema_url()
    try:
        yield make_api(db_url=url)
    finally:
        _pg_drop(schema)


def test_non_finite_odometry_is_refused_at_upload(backend_api: Api, tmp_path: Path) -> None:
    for name, values, pose_only in (("nan", {"wz": NAN}, False), ("huge", {"vx": 1e300}, False),
                                    ("far", {"x": 1e300}, True)):  # fmt: skip
        log = bad_odometry_log(tmp_path / f"{name}.bag", values, None, pose_only=pose_only)
        body = _refused(backend_api, log, None, status=400)
        assert "unusable odometry" in body["detail"] and f"{name}.bag" in body["detail"]
        assert str(tmp_path) not in body["detail"]
    assert nonfinite_floats(backend_api.db_url) == {}


def test_one_bad_odometry_message_is_dropped_and_the_job_says_so(backend_api: Api, tmp_path: Path) -> None:
    log = bad_odometry_log(tmp_path / "one.bag", {"wz": NAN, "x": 1e300}, [100])
    response = backend_api.upload(log, preset="irat")
    assert response.status_code == 202, response.text
    job = backend_api.wait(response.json()["job"])
    assert job["status"] == "done", job
    assert job["dropped"] == {"odometry_messages": 1, "frame_motions": 0,
                              "reasons": {"odometry message: non-finite value": 1}}  # fmt: skip
    session = backend_api.client.get("/v1/maps/one", headers=backend_api.read).json()["sessions"][0]
    assert session["frames"] == 62
    assert len(float_columns(backend_api.db_url)) >= 10  # the check reads every float column of the schema
    assert nonfinite_floats(backend_api.db_url) == {}
    export = backend_api.client.get("/v1/maps/one/export?format=json", headers=backend_api.read)
    assert export.status_code == 200
    clean = bad_odometry_log(tmp_path / "clean.bag", {}, [])
    job = backend_api.wait(backend_api.upload(clean, preset="irat", merge="false").json()["job"])
    assert job["status"] == "done" and job["dropped"] is None


# ------------------------------------------------------------------------------------------ damaged logs
@pytest.mark.parametrize("fmt", ["bag", "db3", "mcap"])
def test_damaged_uploads_are_refused_or_processed_whole(api: Api, tmp_path: Path, fmt: str) -> None:
    data = write_strip_log(tmp_path / f"strip.{fmt}", fmt=fmt).read_bytes()
    for seed in range(12):
        kind, damaged_bytes = damaged(data, seed)
        response = api.client.post("/v1/sessions", files={"file": (f"d{seed}.{fmt}", io.BytesIO(damaged_bytes))},
                                   data={"preset": "irat", "merge": "false"}, headers=api.write)  # fmt: skip
        assert response.status_code in (202, 400), (seed, kind, response.text)
        detail = response.json().get("detail", "")
        assert "Error" not in detail and str(tmp_path) not in detail, detail
        if kind == "truncated":
            assert response.status_code == 400, (seed, response.text)
        if response.status_code == 202 and not response.json()["duplicate"]:
            job = api.wait(response.json()["job"])
            assert job["status"] == "done", (seed, kind, job)
            frames = api.client.get(f"/v1/maps/{job['map']}", headers=api.read).json()["sessions"][0]["frames"]
            assert frames == 62, (seed, kind)


# ------------------------------------------------------------------------------------------ queries, errors
def test_float_queries_refuse_nan_and_infinity(api: Api, tmp_path: Path) -> None:
    job = api.wait(api.upload(write_strip_log(tmp_path / "strip.bag"), preset="irat").json()["job"])
    assert job["status"] == "done"
    base = f"/v1/maps/{job['map']}"
    assert api.client.get(f"{base}/nearest?x=0&y=0", headers=api.read).status_code == 200
    for query in ("x=nan&y=0", "x=0&y=nan", "x=inf&y=0", "x=0&y=-inf", "x=1e300&y=0", "x=NaN&y=NaN"):
        response = api.client.get(f"{base}/nearest?{query}", headers=api.read)
        assert response.status_code == 422, (query, response.text)
        assert response.json()["detail"].startswith("query."), response.json()
    for query in ("resolution=nan", "resolution=inf"):
        assert api.client.get(f"{base}/graph?{query}", headers=api.read).status_code == 422
    for query in ("from=nan&to=1", "from=0&to=inf", "from=0&to=1&weight=nan"):
        assert api.client.get(f"{base}/path?{query}", headers=api.read).status_code == 422


NUMERIC_QUERIES: dict[str, tuple[str, str, list[str]]] = {  # what: (path, good query, bad values)
    "nearest x": ("/nearest", "x={}&y=0", ["nan", "inf", "-inf", "1e300", "1e13", "NaN", "x", ""]),
    "nearest y": ("/nearest", "x=0&y={}", ["nan", "-inf", "-1e300", "-1.1e12"]),
    "graph resolution": ("/graph", "resolution={}", ["nan", "inf", "-1", "1e300", "1e10"]),
    "graph max_nodes": ("/graph", "max_nodes={}", ["nan", "inf", "0", "1e300", "50001", "1.5"]),
    "experiences offset": ("/experiences", "offset={}", ["nan", "inf", "-1", "1e300", "99999999999999999999"]),
    "experiences limit": ("/experiences", "limit={}", ["nan", "inf", "0", "1e300", "10001"]),
    "path from": ("/path", "from={}&to=1", ["nan", "inf", "-1", "1e300", "0.5"]),
    "path to": ("/path", "from=0&to={}", ["nan", "-inf", "1e300", "9223372036854775808"]),
    "node": ("/experiences/{}", "", ["nan", "inf", "-1", "1e300"]),
}
BBOXES = ["nan,0,1,1", "0,0,inf,1", "-inf,-inf,inf,inf", "-1e308,-1e308,1e308,1e308", "-1.1e12,0,1,1",
          "0,0,1e300,1", "1,1,0,0", "0,0,1", "a,b,c,d"]  # fmt: skip


def test_every_numeric_query_refuses_nan_infinity_and_absurd_values(api: Api, tmp_path: Path) -> None:
    """Each number of a REST query: NaN, ±inf, beyond its bound or not a number is a 4xx naming the parameter;
    the value at the bound is answered."""
    job = api.wait(api.upload(write_strip_log(tmp_path / "strip.bag"), preset="irat").json()["job"])
    assert job["status"] == "done"
    base = f"/v1/maps/{job['map']}"
    for what, (path, query, bad) in NUMERIC_QUERIES.items():
        for value in bad:
            url = f"{base}{path.format(value)}?{query.format(value)}" if "{}" in path else \
                f"{base}{path}?{query.format(value)}"  # fmt: skip
            response = api.client.get(url, headers=api.read)
            assert response.status_code in (404, 422), (what, value, response.text)
            detail = response.json()["detail"]
            assert "Error" not in detail and "Traceback" not in detail, (what, value, detail)
            if response.status_code == 422:
                assert detail.startswith(("query.", "path.")), (what, value, detail)
    at_bounds = ["/nearest?x=1e12&y=-1e12", "/graph?resolution=1e9&max_nodes=50000", "/graph?resolution=0",
                 "/experiences?offset=0&limit=10000", "/path?from=0&to=1", "/experiences/0",
                 "/graph?bbox=-1e12,-1e12,1e12,1e12"]  # fmt: skip
    for query in at_bounds:
        response = api.client.get(base + query, headers=api.read)
        assert response.status_code == 200, (query, response.text)
    for bbox in BBOXES:
        response = api.client.get(f"{base}/graph?bbox={bbox}", headers=api.read)
        assert response.status_code == 400, (bbox, response.text)
        assert response.json()["detail"].startswith("bbox "), response.json()
    for path in ("/v1/jobs/{}", "/v1/merges/{}"):
        for value in ("nan", "inf", "0", "1e300", "-1"):
            response = api.client.get(path.format(value), headers=api.read)
            assert response.status_code == 422, (path, value, response.text)


def test_server_errors_carry_no_internal_text(api: Api) -> None:
    secret = "cannot open /srv/private/maps.db: SELECT * FROM maps"
    with mock.patch("mapserver.api.routes.maps.list_maps", side_effect=StoreError(secret)):
        response = api.client.get("/v1/maps", headers=api.read)
    assert response.status_code == 500
    detail = response.json()["detail"]
    assert detail.startswith("internal error (reference ") and "/srv" not in detail and "StoreError" not in detail
    unhandled = TestClient(api.client.app, raise_server_exceptions=False)  # the same running app
    with mock.patch("mapserver.api.routes.maps.list_maps", side_effect=AssertionError("x = 5")):
        response = unhandled.get("/v1/maps", headers=api.read)
    assert response.status_code == 500
    assert response.json()["detail"].startswith("internal error (reference ")
    assert "AssertionError" not in response.json()["detail"] and "5" not in response.json()["detail"].split(")")[-1]


def test_limits_endpoint_lists_every_limit(make_api: Any) -> None:
    api = make_api(max_unpacked_ratio=50.0, max_image_pixels=1_000_000)
    assert api.client.get("/v1/limits").status_code == 401
    body = api.client.get("/v1/limits", headers=api.read).json()
    assert body == {
        "max_upload_bytes": 4 << 30, "max_unpacked_bytes": 8 << 30, "max_unpacked_ratio": 50.0,
        "max_archive_entries": 1000, "max_image_pixels": 1_000_000, "max_trailing_bytes": 1024, "max_exports": 4,
        "read_timeout_s": 60.0,
        "odometry": {"max_position_m": 1e8, "max_speed_m_s": 1e3, "max_yaw_rate_rad_s": 1e2, "max_bad_fraction": 0.05},
        "values": {"max_position_m": 1e8, "max_angle_rad": 1e6, "max_time_s": 1e10, "max_query_coordinate_m": 1e12},
    }  # fmt: skip


# ------------------------------------------------------------------------------------------ a real server
@pytest.fixture
def bombs(tmp_path: Path) -> dict[str, Path]:
    folder = tmp_path / "bombs"
    folder.mkdir()
    return {
        "tar.bz2": zeros_tar(folder / "zeros.tar.bz2", 2 << 30, "bz2"),
        "tar.gz": zeros_tar(folder / "zeros.tar.gz", 1 << 30, "gz"),
        "zip": zeros_zip(folder / "zeros.zip", 256 * MIB),
        "entries": entries_zip(folder / "entries.zip", 20_000),
        "png": payload_bag(folder / "png.bag", [png_bomb(20000, 20000)] * 3, "png"),
        "jpeg": payload_bag(folder / "jpeg.bag", [jpeg_bomb(20000, 20000)] * 3, "jpeg"),
    }


def test_a_served_server_keeps_its_bytes_and_memory_under_the_limits(tmp_path: Path, bombs: dict[str, Path]) -> None:
    """``mapserver serve`` with its flags: every bomb is 413 naming its limit, the server process writes at most
    the upload plus its unpacking budget (``/proc/PID/io`` ``wchar``) and its peak RSS (``VmHWM``) grows by less
    than 64 MiB over all of them; ``GET /v1/limits`` shows the flags."""
    db_url = f"sqlite:///{tmp_path / 'served.db'}"
    server = Server(db_url, tmp_path / "uploads", free_port(), tmp_path / "server.log",
                    extra=("--max-unpacked-ratio", "100", "--max-archive-entries", "500"))  # fmt: skip
    headers = {"Authorization": f"Bearer {make_token(db_url, 'write')}"}
    expected = {"tar.bz2": "max_unpacked_ratio", "tar.gz": "max_unpacked_ratio", "zip": "max_unpacked_ratio",
                "entries": "max_archive_entries", "png": "max_image_pixels", "jpeg": "max_image_pixels"}  # fmt: skip
    try:
        server.start()
        assert server.process is not None
        limits = httpx.get(server.url + "/v1/limits", headers=headers).json()
        assert limits["max_unpacked_ratio"] == 100.0 and limits["max_archive_entries"] == 500
        start = proc_figures(server.process.pid)
        for name, path in bombs.items():
            before = proc_figures(server.process.pid)
            with path.open("rb") as handle:
                response = httpx.post(server.url + "/v1/sessions", files={"file": (path.name, handle)},
                                      data={"preset": "irat"}, headers=headers, timeout=120)  # fmt: skip
            after = proc_figures(server.process.pid)
            assert response.status_code == 413 and response.json()["limit"] == expected[name], response.text
            size = path.stat().st_size
            assert after["wchar"] - before["wchar"] <= size + 100 * size + MIB, (name, after["wchar"] - before["wchar"])
        assert after["VmHWM"] - start["VmHWM"] < 64 * MIB, (start, after)
    finally:
        server.stop()


def test_limits_come_from_the_environment_and_are_checked() -> None:
    from core.config import ConfigError
    from mapserver.api import Settings

    environment = {"MAPSERVER_MAX_UNPACKED_BYTES": "1000", "MAPSERVER_MAX_UNPACKED_RATIO": "2.5",
                   "MAPSERVER_MAX_ARCHIVE_ENTRIES": "7", "MAPSERVER_MAX_IMAGE_PIXELS": "99"}  # fmt: skip
    settings = Settings.from_env(environment)
    assert settings.limits() == {"max_upload_bytes": 4 << 30, "max_unpacked_bytes": 1000, "max_unpacked_ratio": 2.5,
                                 "max_archive_entries": 7, "max_image_pixels": 99, "max_trailing_bytes": 1024,
                                 "max_exports": 4, "read_timeout_s": 60.0}  # fmt: skip
    for bad in ({"MAPSERVER_MAX_UNPACKED_RATIO": "nan"}, {"MAPSERVER_MAX_UNPACKED_RATIO": "0.5"},
                {"MAPSERVER_MAX_ARCHIVE_ENTRIES": "0"}, {"MAPSERVER_MAX_IMAGE_PIXELS": "lots"}):  # fmt: skip
        with pytest.raises(ConfigError):
            Settings.from_env(bad)

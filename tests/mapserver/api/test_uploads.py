"""Upload safety: non-bags, truncated bags, oversized uploads, archives (valid and hostile)."""

from __future__ import annotations

import io
import tarfile
import zipfile
from pathlib import Path
from typing import Any

import pytest

from mapserver.errors import InputError
from tests.mapserver.api.conftest import Api
from tests.mapserver.api.logs import tar_bytes, write_strip_log, zip_directory


def _files(api: Api) -> list[Path]:
    return sorted(p for p in api.settings.uploads.rglob("*") if p.is_file())


def _jobs(api: Api) -> int:
    from mapserver.store import open_database
    from mapserver.store.jobs import count_jobs

    with open_database(api.db_url) as db, db.read() as conn:
        return sum(count_jobs(conn=conn).values())


def _post_bytes(api: Api, name: str, data: bytes, **fields: str) -> Any:
    return api.client.post("/v1/sessions", files={"file": (name, io.BytesIO(data))}, data=fields, headers=api.write)


def test_non_bag_is_400_with_the_reason(api: Api) -> None:
    response = _post_bytes(api, "notes.bag", b"this is not a bag at all\n" * 100)
    assert response.status_code == 400
    detail = response.json()["detail"]
    assert "not a readable bag" in detail and "notes.bag" in detail
    assert str(api.settings.uploads) not in detail  # the server's paths are not shown
    assert _files(api) == [] and _jobs(api) == 0


def test_unsupported_type_is_400(api: Api) -> None:
    response = _post_bytes(api, "photo.jpg", b"\xff\xd8\xff" + b"0" * 100)
    assert response.status_code == 400
    assert "unsupported upload 'photo.jpg'" in response.json()["detail"]
    assert _files(api) == []


def test_truncated_bag_is_400(api: Api, strip_log: Path) -> None:
    data = strip_log.read_bytes()
    response = _post_bytes(api, "cut.bag", data[: len(data) // 2])
    assert response.status_code == 400
    assert "cut.bag" in response.json()["detail"]
    assert _files(api) == [] and _jobs(api) == 0


def test_an_unknown_preset_is_400_with_the_engines_message(api: Api, strip_log: Path) -> None:
    """The engine's ConfigError (one class for core and mapserver) is a 400 naming the presets, writing nothing."""
    from core.config import ConfigError, preset

    with pytest.raises(ConfigError) as refused:
        preset("cirkle")
    response = api.upload(strip_log, preset="cirkle")
    assert response.status_code == 400 and response.json() == {"detail": str(refused.value)}
    assert "did you mean 'circle'" in response.json()["detail"]
    assert _files(api) == [] and _jobs(api) == 0
    assert api.upload(strip_log, preset="circle").status_code == 202  # the same log with a preset that exists


def test_bad_form_fields_are_400(api: Api, strip_log: Path) -> None:
    cases = {
        ("preset", "nope"): "nope",
        ("topics", "image"): "KEY=TOPIC",
        ("topics", '{"image": 3}'): "JSON object of strings",
        ("merge", "maybe"): "merge must be true or false",
        ("colour", "red"): "unknown form field",
        ("map", " "): "invalid map name",
    }
    for (key, value), expected in cases.items():
        response = api.upload(strip_log, **{key: value})
        assert response.status_code == 400, (key, response.text)
        assert expected in response.json()["detail"], (key, response.json())
    wrong_topic = api.upload(strip_log, topics="image=/no/such/topic", preset="irat")
    assert wrong_topic.status_code == 400
    assert "/no/such/topic" in wrong_topic.json()["detail"]
    assert _files(api) == [] and _jobs(api) == 0


def test_not_multipart_is_415_and_missing_file_is_400(api: Api) -> None:
    response = api.client.post("/v1/sessions", content=b"{}", headers={**api.write, "Content-Type": "application/json"})
    assert response.status_code == 415
    no_file = api.client.post("/v1/sessions", data={"preset": "irat"}, files={"other": ("a.txt", b"x")},
                              headers=api.write)  # fmt: skip
    assert no_file.status_code == 400


def test_oversized_upload_is_413_and_nothing_is_kept(make_api: Any, strip_log: Path) -> None:
    api = make_api(max_upload_bytes=100_000)
    assert strip_log.stat().st_size > 100_000
    response = api.upload(strip_log, preset="irat")
    assert response.status_code == 413
    assert "limit of 100000 bytes" in response.json()["detail"]
    assert _files(api) == [] and _jobs(api) == 0


def test_oversized_streamed_body_without_length_is_413(make_api: Any) -> None:
    """A chunked body (no Content-Length) is cut off while streaming, as soon as it passes the limit."""
    api = make_api(max_upload_bytes=50_000)
    boundary = "b0undary"

    def body() -> Any:
        yield (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"big.bag\"\r\n"
               "Content-Type: application/octet-stream\r\n\r\n").encode()  # fmt: skip
        for _ in range(100):
            yield b"x" * 10_000
        yield f"\r\n--{boundary}--\r\n".encode()

    content_type = f"multipart/form-data; boundary={boundary}"
    response = api.client.post("/v1/sessions", content=body(), headers={**api.write, "Content-Type": content_type})
    assert response.status_code == 413
    assert _files(api) == []


@pytest.mark.parametrize("kind", ["zip", "tar.gz"])
def test_ros2_bag_directory_archive(api: Api, tmp_path: Path, kind: str) -> None:
    bag_dir = write_strip_log(tmp_path / "logs" / "rosbag2_mission", fmt="db3", directory=True)
    assert bag_dir.is_dir() and (bag_dir / "metadata.yaml").is_file()
    out = tmp_path / "archives"
    out.mkdir()
    if kind == "zip":
        archive = zip_directory(bag_dir, out / "mission.zip")
    else:
        archive = out / "mission.tar.gz"
        with tarfile.open(archive, "w:gz") as tf:
            tf.add(bag_dir, arcname=bag_dir.name)
    response = api.upload(archive, preset="irat")
    assert response.status_code == 202, response.text
    job = api.wait(response.json()["job"])
    assert job["status"] == "done", job
    assert job["session"] == "rosbag2_mission"


def _zip_with(entries: list[tuple[zipfile.ZipInfo | str, bytes]]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as zf:
        for info, data in entries:
            zf.writestr(info, data)
    return buffer.getvalue()


def _symlink_zip() -> bytes:
    info = zipfile.ZipInfo("bag/link")
    info.external_attr = (0o120777 << 16)
    return _zip_with([("bag/metadata.yaml", b"x"), (info, b"/etc/passwd")])


def _tar_member(name: str, kind: bytes, linkname: str = "") -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type = kind
    info.linkname = linkname
    return info


HOSTILE: dict[str, tuple[str, bytes, str]] = {
    "zip-dotdot": ("evil.zip", _zip_with([("../outside.txt", b"x")]), "'..'"),
    "zip-absolute": ("evil.zip", _zip_with([("/tmp/abs.txt", b"x")]), "absolute path"),
    "zip-backslash": ("evil.zip", _zip_with([("..\\win.txt", b"x")]), "unsafe name"),
    "zip-symlink": ("evil.zip", _symlink_zip(), "symbolic link"),
    "tar-dotdot": ("evil.tar", tar_bytes([(tarfile.TarInfo("a/../../escape.txt"), b"x")]), "'..'"),
    "tar-absolute": ("evil.tar", tar_bytes([(tarfile.TarInfo("/etc/cron.d/x"), b"x")]), "absolute path"),
    "tar-symlink": ("evil.tar", tar_bytes([(_tar_member("bag/link", tarfile.SYMTYPE, "/etc/passwd"), None)]), "link"),
    "tar-hardlink": ("evil.tar", tar_bytes([(_tar_member("bag/hard", tarfile.LNKTYPE, "/etc/passwd"), None)]), "link"),
    "tar-device": ("evil.tar", tar_bytes([(_tar_member("bag/dev", tarfile.CHRTYPE), None)]), "special file"),
    "tar-fifo": ("evil.tar", tar_bytes([(_tar_member("bag/fifo", tarfile.FIFOTYPE), None)]), "special file"),
    "not-an-archive": ("junk.zip", b"PK but not really" * 10, "not a readable .zip archive"),
    "empty-of-logs": ("empty.zip", _zip_with([("readme.txt", b"hello")]), "no ROS 2 bag directory"),
}


@pytest.mark.parametrize("case", list(HOSTILE))
def test_hostile_archives_are_refused(api: Api, tmp_path: Path, case: str) -> None:
    name, data, expected = HOSTILE[case]
    response = _post_bytes(api, name, data)
    assert response.status_code == 400, response.text
    assert expected in response.json()["detail"]
    assert _files(api) == [] and _jobs(api) == 0
    assert not (api.settings.uploads.parent / "outside.txt").exists()
    assert not Path("/tmp/abs.txt").exists()


def test_zip_bomb_stops_at_the_unpacked_limit(make_api: Any) -> None:
    api = make_api(max_unpacked_bytes=1_000_000)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("bag/metadata.yaml", b"rosbag2_bagfile_information: {}\n")
        zf.writestr("bag/bomb.db3", b"\0" * 20_000_000)
    data = buffer.getvalue()
    assert len(data) < 100_000
    response = _post_bytes(api, "bomb.zip", data)
    assert response.status_code == 413
    assert response.json()["limit"] == "max_unpacked_bytes"
    assert "limit is max_unpacked_bytes = 1000000" in response.json()["detail"]
    assert _files(api) == []


def test_zip_with_lying_headers_is_refused(make_api: Any) -> None:
    """A zip whose headers under-state an entry's size is refused (nothing unpacked beyond what it declares)."""
    from mapserver.api.archives import ArchiveLimits, extract_archive

    api = make_api()
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("bag/bomb.db3", b"\0" * 3_000_000)
    raw = bytearray(buffer.getvalue())
    # patch the declared uncompressed size in the central directory (offset 24 of the entry) to 10 bytes
    central = raw.rfind(b"PK\x01\x02")
    raw[central + 24: central + 28] = (10).to_bytes(4, "little")
    archive = api.settings.uploads / "lying.zip"
    archive.parent.mkdir(parents=True, exist_ok=True)
    archive.write_bytes(bytes(raw))
    dest = api.settings.uploads / "lying"
    with pytest.raises(InputError, match=r"archive"):
        extract_archive(archive, dest, kind=".zip", limits=ArchiveLimits(1_000_000, 1e6, 10))
    assert not dest.exists()


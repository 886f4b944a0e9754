"""``mapserver process`` end to end: summary, map JSON with the per-frame record, and every bad-input case."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import pytest

from mapserver.cli import main
from mapserver.formats import read_map_json
from mapserver.ingest.writer import write_log
from tests.mapserver.ingest.conftest import (
    arc_odometry,
    frame_images,
    identity_gt,
    image_msg,
    test_image,
    write_raw,
)

IMG = "sensor_msgs/msg/Image"
SUMMARY_KEYS = {"frames", "templates", "experiences", "links", "loop_closures", "merges", "map", "seconds"}


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def small_log(tmp_path: Path) -> Path:
    odometry = arc_odometry(61, 20.0, v=0.5, w=0.2)
    images = [(stamp, test_image(i, False, (48, 128))) for i, (stamp, _) in enumerate(frame_images(30, 10.0, False))]
    return write_log(tmp_path / "mission", "mcap", images, odometry, identity_gt(odometry))


def test_process_json_summary_and_map_with_frame_record(
    small_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out_map = tmp_path / "map.json"
    code, out, err = _run(capsys, "process", str(small_log), "--preset", "poseidon", "--out", str(out_map), "--json")
    assert code == 0
    summary = json.loads(out.strip().splitlines()[-1])
    assert set(summary) >= SUMMARY_KEYS
    assert summary["frames"] == 30 and summary["merges"] == [] and summary["map"] == "mission"
    assert "30 frames" in err
    doc = read_map_json(out_map)
    rows = doc["frames"]
    assert len(rows) == 30 and len(doc["odometry"]) == 30
    assert rows[0][2] == 1  # the first frame always creates template 0
    created = sorted({int(r[1]) for r in rows if r[2] == 1})
    assert created == list(range(doc["templates"]))  # each template created exactly once, in id order
    assert [r[0] for r in rows] == sorted(r[0] for r in rows)
    assert summary["templates"] == doc["templates"] and summary["experiences"] == len(doc["experiences"])
    assert "nothing was kept" not in err  # must not: a warning when the map is written


def test_process_with_nowhere_to_keep_the_map_warns_and_still_summarises(
    small_log: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _, err = _run(capsys, "process", str(small_log), "--preset", "poseidon")
    assert code == 0
    assert err.strip().splitlines()[-1] == (
        "warning: nothing was kept: give --out MAP.json to write the map, or --db URL to store it"
    )
    assert "30 frames" in err  # must still: the summary


def _not_a_bag(tmp_path: Path) -> Path:
    path = tmp_path / "notes.bag"
    path.write_text("this is not a bag\n" * 50)
    return path


def _truncated(tmp_path: Path) -> Path:
    odometry = arc_odometry(200, 20.0)
    path = write_log(tmp_path / "full", "bag", frame_images(100, 10.0, True), odometry, image_encoding="rgb8")
    cut = tmp_path / "cut.bag"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    path.unlink()
    return cut


def _corrupt_middle(tmp_path: Path) -> Path:
    """A ROS 1 bag whose middle 4 kB are zeroed: opens fine, fails while streaming."""
    odometry = arc_odometry(200, 20.0)
    images = [(s, test_image(i, True, (48, 128))) for i, (s, _) in enumerate(frame_images(100, 10.0, True))]
    path = write_log(tmp_path / "full", "bag", images, odometry, image_encoding="rgb8")
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 4000] = bytes(4000)
    bad = tmp_path / "zeroed.bag"
    bad.write_bytes(bytes(data))
    path.unlink()
    return bad


def _corrupt_mcap_with_checksums(tmp_path: Path) -> Path:
    """An MCAP log whose chunks carry CRC-32s (as the ``ros2 bag record`` writer stores them) and whose last
    chunk then has one byte flipped.

    rosbags' own writer stores CRC 0 ("not computed", allowed by the MCAP spec), and a chunk without a checksum
    cannot be verified by anyone; the reader verifies every chunk that has one. The CRCs are patched in here by
    walking the records: opcode (1 byte), length (uint64), then for a Chunk (0x06) start/end time, uncompressed
    size (uint64 each), the CRC (uint32), the compression name and the uint64-sized records.
    """
    odometry = arc_odometry(200, 20.0)
    images = [(s, test_image(i, True, (48, 128))) for i, (s, _) in enumerate(frame_images(100, 10.0, True))]
    path = write_log(tmp_path / "full", "mcap", images, odometry, image_encoding="rgb8")
    data = bytearray(path.read_bytes())
    offset, chunks = 8, []  # after the magic
    while offset < len(data) - 8:
        opcode = data[offset]
        (length,) = struct.unpack_from("<Q", data, offset + 1)
        body = offset + 9
        if opcode == 0x06:
            (name_len,) = struct.unpack_from("<I", data, body + 28)
            assert bytes(data[body + 32 : body + 32 + name_len]) == b""  # uncompressed chunks
            records = body + 32 + name_len + 8
            (records_len,) = struct.unpack_from("<Q", data, records - 8)
            struct.pack_into("<I", data, body + 24, zlib.crc32(data[records : records + records_len]))
            chunks.append((records, records_len))
        elif opcode == 0x0F:  # footer
            break
        offset = body + length
    assert len(chunks) >= 2
    records, records_len = chunks[-1]
    data[records + records_len // 2] ^= 0xFF
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(bytes(data))
    path.unlink()
    return bad


def _no_camera(tmp_path: Path) -> Path:
    return write_log(tmp_path / "odom_only", "db3", [], arc_odometry(20, 20.0))


def _unsupported_encoding(tmp_path: Path) -> Path:
    return write_raw(tmp_path / "yuv.bag", "bag", [("/cam/image", IMG, lambda ts, s: image_msg(ts, s, "yuv422"), 3)])


def _missing(tmp_path: Path) -> Path:
    return tmp_path / "nowhere.bag"


@pytest.mark.parametrize(
    ("make", "reason"),
    [
        (_not_a_bag, "not a readable bag"),
        (_truncated, ""),
        (_corrupt_middle, "corrupt log"),
        (_corrupt_mcap_with_checksums, "checksum mismatch"),
        (_no_camera, "no camera topic: process needs sensor_msgs/Image or CompressedImage"),
        (_unsupported_encoding, "unsupported image encoding 'yuv422'"),
        (_missing, "not found"),
    ],
)
def test_bad_logs_are_one_line_exit_2_and_write_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], make: object, reason: str
) -> None:
    log = make(tmp_path)  # type: ignore[operator]
    out_map = tmp_path / "out" / "map.json"
    out_map.parent.mkdir()
    code, out, err = _run(capsys, "process", str(log), "--preset", "poseidon", "--out", str(out_map), "--json")
    assert code == 2
    assert out == ""
    lines = err.strip().splitlines()
    error_lines = [line for line in lines if line.startswith("ERROR:")]
    assert len(error_lines) == 1 and reason in error_lines[0] and str(log) in error_lines[0]
    assert list(out_map.parent.iterdir()) == []  # nothing written, no temporary left


def test_images_too_small_for_the_preset_are_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = write_log(tmp_path / "tiny", "bag", frame_images(3, 10.0, False), arc_odometry(7, 20.0))
    out_map = tmp_path / "map.json"
    code, _, err = _run(capsys, "process", str(log), "--preset", "poseidon-lvc", "--out", str(out_map))
    assert code == 2 and "smaller than the 64×24 template" in err and str(log) in err
    assert not out_map.exists()


def test_bad_preset_and_topics_are_exit_2(small_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = _run(capsys, "process", str(small_log), "--preset", "cirkle")
    assert code == 2 and "unknown preset 'cirkle'" in err and "circle" in err
    code, _, err = _run(capsys, "process", str(small_log), "--topics", "image=/nope")
    assert code == 2 and "'/nope'" in err


def test_merge_flags_need_a_database(capsys: pytest.CaptureFixture[str], small_log: Path) -> None:
    for flag in (["--confirm", "1"], ["--merge-no-shift"]):
        code, _out, err = _run(capsys, "process", str(small_log), *flag)
        assert code == 2
        expected = "ERROR: --confirm and --merge-no-shift need --db (merging is into stored maps)"
        assert err.strip().splitlines()[-1] == expected
    code, _out, err = _run(capsys, "process", str(small_log), "--db", "sqlite:///:memory:", "--confirm", "0")
    assert code == 2 and err.strip().splitlines()[-1] == "ERROR: --confirm must be at least 1, got 0"


def test_merge_no_shift_is_marked_as_a_debug_flag(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["process", "--help"])
    assert "DEBUG: merge without operation (iii)" in " ".join(capsys.readouterr().out.split())


def test_the_rate_counts_the_frames_of_this_run() -> None:
    from mapserver.processing.pipeline import ProcessResult

    resumed = ProcessResult(frames=100, templates=1, experiences=1, links=0, loop_closures=0, map_name="m",
                            seconds=2.0, frames_run=10)  # fmt: skip
    assert resumed.summary()["frames_per_s"] == 5.0


@pytest.mark.parametrize("with_db", [False, True])
def test_the_clock_starts_after_the_front_end_is_loaded(
    small_log: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, with_db: bool
) -> None:
    """Loading the view module's libraries (torch: ~2 s) is program start, not the log's processing."""
    import time

    import mapserver.processing.run
    from core.config import preset
    from mapserver.processing.pipeline import process_into_store, process_log

    loaded = []

    def slow_load(params: object) -> type:
        time.sleep(0.6)
        loaded.append(params)
        return object

    monkeypatch.setattr(mapserver.processing.run, "view_cells_class", slow_load)
    started = time.perf_counter()
    if with_db:
        result = process_into_store(small_log, preset("poseidon"), db_url=f"sqlite:///{tmp_path / 'db.sqlite'}")
    else:
        result = process_log(small_log, preset("poseidon"))
    elapsed = time.perf_counter() - started
    assert len(loaded) == 1 and result.frames == 30
    assert result.seconds < elapsed - 0.5  # the 0.6 s load is outside the run's seconds


def test_set_changes_engine_parameters_on_top_of_the_preset(
    small_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--set`` applies keys over ``--preset``: the map JSON records them and the preset's own values stay."""
    plain, joint = tmp_path / "plain.json", tmp_path / "joint.json"
    assert _run(capsys, "process", str(small_log), "--preset", "poseidon-lvc", "--out", str(plain))[0] == 0
    code, _, _ = _run(capsys, "process", str(small_log), "--preset", "poseidon-lvc", "--out", str(joint),
                      "--set", "exp_relax_joint=1, vt_match_threshold=0.07")  # fmt: skip
    assert code == 0
    before, after = read_map_json(plain)["params"], read_map_json(joint)["params"]
    assert (before["exp_relax_joint"], after["exp_relax_joint"]) == (False, True)
    assert (before["vt_match_threshold"], after["vt_match_threshold"]) == (0.06, 0.07)
    assert after["pc_dim_xy"] == before["pc_dim_xy"] == 15  # the rest is poseidon-lvc's
    repeated = tmp_path / "repeated.json"  # every --set applies, not only the last one
    code, _, _ = _run(capsys, "process", str(small_log), "--preset", "poseidon-lvc", "--out", str(repeated),
                      "--set", "exp_relax_joint=1", "--set", "vt_match_threshold=0.07")  # fmt: skip
    assert code == 0 and read_map_json(repeated)["params"] == after


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("exp_relax_jiont=1", "unknown parameter 'exp_relax_jiont' in --set (did you mean 'exp_relax_joint'?)"),
        ("exp_relax_joint", "bad --set entry 'exp_relax_joint': expected KEY=VALUE, e.g. vt_shift_heading=1"),
        ("exp_relax_joint=1,exp_relax_joint=0", "bad --set: 'exp_relax_joint' given twice"),
        (("exp_relax_joint=1", "exp_relax_joint=0"), "bad --set: 'exp_relax_joint' given twice"),  # two --set
        ("vt_match_threshold=-1", "vt_match_threshold"),
    ],
)
def test_a_bad_set_is_exit_2_and_writes_nothing(
    small_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], setting: str | tuple[str, ...], message: str
) -> None:
    out_map = tmp_path / "map.json"
    sets = [f"--set={s}" for s in ((setting,) if isinstance(setting, str) else setting)]
    code, _, err = _run(capsys, "process", str(small_log), "--out", str(out_map), *sets)
    assert code == 2 and message in err and err.count("\n") == 1
    assert not out_map.exists()

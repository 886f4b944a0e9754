"""Hostile logs at the ingest edge: image bombs, non-finite and absurd odometry, damaged files (issue 61).

Each refusal is paired with an ordinary input at the limit that is still processed.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from unittest import mock

import cv2
import numpy as np
import pytest

from core.motion import Motion
from mapserver.cli import main
from mapserver.errors import IngestError, LimitError
from mapserver.ingest import decode
from mapserver.ingest.decode import compressed_size, decode_image, set_max_image_pixels
from mapserver.ingest.odometry import (
    MAX_SPEED_M_S,
    OdometryCheck,
    OdometryState,
    motion_problem,
    state_problem,
)
from mapserver.ingest.reader import open_log
from tests.mapserver.api.logs import write_strip_log
from tests.mapserver.hostile import (
    bad_odometry_log,
    damaged,
    encoded,
    jpeg_bomb,
    nonfinite_floats,
    payload_bag,
    png_bomb,
)

ROOT = Path(__file__).resolve().parents[3]
NAN, INF = float("nan"), float("inf")


@pytest.fixture(autouse=True)
def _process_pixel_limit() -> Iterator[None]:
    """``process --max-image-pixels`` sets the process's limit: every test starts and ends with the default."""
    previous = set_max_image_pixels(None)
    yield
    set_max_image_pixels(previous)


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def _error_line(err: str) -> str:
    lines = [line for line in err.strip().splitlines() if line.startswith("ERROR")]
    assert len(lines) == 1, err
    assert "Traceback" not in err and "AssertionError" not in err, err
    return lines[0]


def _compressed(data: bytes, fmt: str = "png") -> SimpleNamespace:
    return SimpleNamespace(format=fmt, data=np.frombuffer(data, np.uint8))


# ------------------------------------------------------------------------------------------- image bombs
@pytest.mark.parametrize("kind", ["png", "jpeg", "jpeg-progressive"])
def test_image_bombs_are_refused_from_their_header_before_decoding(kind: str) -> None:
    payload = {"png": lambda: png_bomb(20000, 20000), "jpeg": lambda: jpeg_bomb(20000, 20000),
               "jpeg-progressive": lambda: jpeg_bomb(20000, 20000, progressive=True)}[kind]()  # fmt: skip
    assert len(payload) < 600_000  # ~400 KB of PNG, a few hundred bytes of JPEG: 400 Mpx decoded
    assert compressed_size(payload) == (20000, 20000)
    expected = r"20000x20000 = 400000000 pixels.*max_image_pixels = 33554432"
    with mock.patch.object(decode.cv2, "imdecode", side_effect=AssertionError("decoded")) as imdecode, \
            pytest.raises(LimitError, match=expected) as err:  # fmt: skip
        decode_image(_compressed(payload, kind.split("-")[0]), "/cam")
    assert err.value.limit == "max_image_pixels" and imdecode.call_count == 0


@pytest.mark.parametrize("fmt", ["png", "jpeg"])
def test_an_image_at_the_pixel_limit_decodes_and_one_pixel_less_refuses(fmt: str) -> None:
    message = _compressed(encoded(fmt, 64, 48), fmt)
    assert decode_image(message, "/cam", max_pixels=64 * 48).shape == (48, 64)
    with pytest.raises(LimitError, match="3072 pixels, more than the limit max_image_pixels = 3071"):
        decode_image(message, "/cam", max_pixels=64 * 48 - 1)


def test_raw_images_are_limited_by_width_times_height_and_corrupt_ones_stay_corrupt() -> None:
    raw = SimpleNamespace(encoding="mono8", height=48, width=64, step=64, is_bigendian=0,
                          data=np.zeros(64 * 48, np.uint8))  # fmt: skip
    assert decode_image(raw, "/cam", max_pixels=64 * 48).shape == (48, 64)
    with pytest.raises(LimitError, match="max_image_pixels = 100"):
        decode_image(raw, "/cam", max_pixels=100)
    lying = SimpleNamespace(**{**vars(raw), "height": 1 << 27})  # a flipped bit: not a limit, a corrupt image
    with pytest.raises(IngestError, match="corrupt image") as err:
        decode_image(lying, "/cam", max_pixels=100)
    assert not isinstance(err.value, LimitError)


def test_payloads_that_are_neither_jpeg_nor_png_are_refused() -> None:
    _ok, bmp = cv2.imencode(".bmp", np.zeros((8, 8), np.uint8))
    for data in (bmp.tobytes(), b"\xff\xd8\xff\xd9", b"\x89PNG\r\n\x1a\n" + bytes(8)):
        with pytest.raises(IngestError, match="no JPEG or PNG header"):
            decode_image(_compressed(data), "/cam")


def _peak_rss_of_process(log: Path, *extra: str) -> tuple[int, int, str]:
    """Run ``mapserver process`` in a child process; return its exit code, peak RSS (bytes) and stderr."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    child = subprocess.Popen(
        [sys.executable, "-c", "import sys; from mapserver.cli import entry; sys.argv[0] = 'mapserver'; entry()",
         "process", str(log), "--preset", "irat", *extra], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
    )  # fmt: skip
    assert child.stderr is not None
    err = child.stderr.read().decode()
    _pid, status, usage = os.wait4(child.pid, 0)
    return os.waitstatus_to_exitcode(status), usage.ru_maxrss * 1024, err


def test_process_refuses_an_image_bomb_bag_in_one_line_without_the_memory(tmp_path: Path) -> None:
    """Three 20000×20000 PNG frames (400 MB each decoded) in a ~1.2 MB bag: exit 2, and the child's peak RSS
    stays within 64 MiB of processing an ordinary log (one decoded bomb frame alone is 400 MB)."""
    code, ordinary, err = _peak_rss_of_process(write_strip_log(tmp_path / "strip.bag"))
    assert code == 0, err
    bag = payload_bag(tmp_path / "bomb.bag", [png_bomb(20000, 20000)] * 3, "png")
    assert bag.stat().st_size < 2_000_000
    code, peak, err = _peak_rss_of_process(bag)
    assert code == 2
    assert "max_image_pixels = 33554432" in _error_line(err)
    assert peak < ordinary + 64 * (1 << 20), (peak, ordinary)


def test_process_max_image_pixels_flag_pairs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = write_strip_log(tmp_path / "strip.bag")  # 64×20 frames: 1280 pixels
    code, out, _err = _run(capsys, "process", str(log), "--preset", "irat", "--max-image-pixels", "1280", "--json")
    assert code == 0 and json.loads(out.strip().splitlines()[-1])["frames"] == 62
    code, _out, err = _run(capsys, "process", str(log), "--preset", "irat", "--max-image-pixels", "1279")
    assert code == 2
    assert "1280 pixels, more than the limit max_image_pixels = 1279" in _error_line(err)


def test_a_bomb_after_ordinary_frames_fails_the_run_and_stores_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    frames = [encoded("png", 64, 20, seed=k) for k in range(6)] + [png_bomb(20000, 20000)]
    bag = payload_bag(tmp_path / "late.bag", frames, "png")
    db_url = f"sqlite:///{tmp_path / 'late.db'}"
    code, _out, err = _run(capsys, "process", str(bag), "--preset", "irat", "--db", db_url)
    assert code == 2 and "max_image_pixels" in _error_line(err)
    assert _stored_maps(db_url) == []


def _stored_maps(db_url: str) -> list[object]:
    from mapserver.store import open_database
    from mapserver.store.maps import list_maps

    with open_database(db_url) as db, db.read() as conn:
        return list(list_maps(conn=conn))


# ------------------------------------------------------------------------------------------- odometry
def _state(**values: float) -> OdometryState:
    base = {"stamp_ns": 0, "x": 0.0, "y": 0.0, "z": 0.0, "yaw": 0.0, "forward": 1.0, "lateral": 0.0,
            "vertical": 0.0, "yaw_rate": 0.1}  # fmt: skip
    return OdometryState(**{**base, **values})  # type: ignore[arg-type]


def test_state_and_motion_bounds() -> None:
    assert state_problem(_state()) is None
    assert state_problem(_state(x=1e8, forward=1e3, yaw_rate=1e2)) is None  # at the bounds
    assert state_problem(_state(yaw_rate=NAN)) == "non-finite value"
    assert state_problem(_state(yaw=INF)) == "non-finite value"
    assert state_problem(_state(y=-1.1e8)) == "position beyond 1e+08 m"
    assert state_problem(_state(forward=1e300)) == "speed above 1000 m/s"
    assert state_problem(_state(lateral=800.0, vertical=800.0)) == "speed above 1000 m/s"
    assert state_problem(_state(yaw_rate=-101.0)) == "yaw rate above 100 rad/s"
    assert motion_problem(Motion(500.0, 0.0, 0.0, 3.0, 0.5)) is None
    assert motion_problem(Motion(501.0, 0.0, 0.0, 0.0, 0.5)) == "faster than 1000 m/s"
    assert motion_problem(Motion(0.0, 0.0, 0.0, NAN, 0.5)) == "non-finite value"
    assert motion_problem(Motion(1.0, 0.0, 0.0, 0.0, 0.0)) == "faster than 1000 m/s"  # moved in no time


def test_check_drops_and_counts_then_refuses_past_five_percent() -> None:
    check = OdometryCheck(messages=100, frames=40, source="log.bag")
    for _ in range(5):  # 5 of 100: kept going
        assert check.accept(_state(yaw_rate=NAN)) is False
    assert check.accept(_state()) is True
    expected = (r"log.bag: unusable odometry: 6 of the log's 100 odometry messages dropped "
                r"\(non-finite value: 6\); a log is refused when more than 5% are")  # fmt: skip
    with pytest.raises(IngestError, match=expected):
        check.accept(_state(yaw_rate=NAN))
    motions = OdometryCheck(messages=0, frames=40)
    assert motions.motion(Motion(1e6, 0.0, 0.0, 0.0, 0.5)) == Motion(0.0, 0.0, 0.0, 0.0, 0.5)
    assert motions.motion(Motion(1.0, 0.0, 0.0, 0.1, 0.5)) == Motion(1.0, 0.0, 0.0, 0.1, 0.5)
    assert motions.motion(Motion(NAN, 0.0, 0.0, 0.0, 0.5)) == Motion(0.0, 0.0, 0.0, 0.0, 0.5)
    assert motions.report.as_dict() == {
        "odometry_messages": 0, "frame_motions": 2,
        "reasons": {"frame motion: faster than 1000 m/s": 1, "frame motion: non-finite value": 1},
    }  # fmt: skip
    with pytest.raises(IngestError, match="3 of the log's 40 frames' motions dropped"):
        motions.motion(Motion(MAX_SPEED_M_S, 0.0, 0.0, 0.0, 0.5))


REFUSED = {
    "nan-yaw-rate": ({"wz": NAN}, False, "non-finite value"),
    "inf-speed": ({"vx": INF}, False, "non-finite value"),
    "vx-1e300": ({"vx": 1e300}, False, "speed above 1000 m/s"),
    "poses-1e300": ({"x": 1e300}, True, "position beyond 1e+08 m"),
    "nan-yaw-pose": ({"yaw": NAN}, True, "non-finite value"),
}


@pytest.mark.parametrize("case", list(REFUSED))
def test_non_finite_or_absurd_odometry_refuses_the_log_and_stores_nothing(
    case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    values, pose_only, reason = REFUSED[case]
    log = bad_odometry_log(tmp_path / f"{case}.bag", values, None, pose_only=pose_only)
    db_url = f"sqlite:///{tmp_path / 'bad.db'}"
    code, out, err = _run(capsys, "process", str(log), "--preset", "irat", "--db", db_url, "--json")
    assert code == 2 and out == ""
    line = _error_line(err)
    assert "unusable odometry" in line and reason in line and "refused when more than 5%" in line
    assert _stored_maps(db_url) == []
    assert nonfinite_floats(db_url) == {}


@pytest.mark.parametrize("fmt", ["bag", "mcap"])
def test_one_bad_message_among_many_is_dropped_counted_and_the_map_is_whole(
    fmt: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = bad_odometry_log(tmp_path / f"one.{fmt}", {"wz": NAN, "vx": 1e300}, [100], fmt=fmt)
    db_url = f"sqlite:///{tmp_path / 'one.db'}"
    code, out, err = _run(capsys, "process", str(log), "--preset", "irat", "--db", db_url, "--json")
    assert code == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["frames"] == 62
    assert summary["dropped"] == {"odometry_messages": 1, "frame_motions": 0,
                                  "reasons": {"odometry message: non-finite value": 1}}  # fmt: skip
    assert "warning: dropped 1 of 307 odometry messages (non-finite value: 1)" in err
    assert nonfinite_floats(db_url) == {}


def test_a_pose_jump_drops_the_two_frame_motions_across_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Pose odometry with one pose 1e6 m off (finite, within the position bound): the two frames around it lose
    their motion (it would mean 2,000 km/s); the map stays where the robot drove."""
    log = bad_odometry_log(tmp_path / "jump.bag", {"x": 1e6}, [100], pose_only=True)
    out_json = tmp_path / "jump.json"
    code, out, err = _run(capsys, "process", str(log), "--preset", "irat", "--json", "--out", str(out_json))
    assert code == 0, err
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["frames"] == 62 and summary["dropped"]["frame_motions"] == 2
    assert summary["dropped"]["reasons"] == {"frame motion: faster than 1000 m/s": 2}
    poses = np.array([[e["x"], e["y"]] for e in json.loads(out_json.read_text())["experiences"]])
    assert np.isfinite(poses).all() and np.abs(poses).max() < 50.0  # the strip's circle has a radius of 3.8 m


def test_verify_reads_every_topic_and_refuses_bad_odometry_before_any_frame(tmp_path: Path) -> None:
    good = write_strip_log(tmp_path / "good.bag")
    with open_log(good) as log:
        assert log.verify().as_dict()["odometry_messages"] == 0
    bad = bad_odometry_log(tmp_path / "bad.bag", {"vx": NAN}, list(range(0, 300, 5)))
    with open_log(bad) as log, pytest.raises(IngestError, match="unusable odometry"):
        log.verify()


# ------------------------------------------------------------------------------------------- damaged logs
FORMATS = ("bag", "db3", "mcap")


@pytest.fixture(scope="module")
def clean_logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    folder = tmp_path_factory.mktemp("clean")
    return {fmt: write_strip_log(folder / f"strip.{fmt}", fmt=fmt).read_bytes() for fmt in FORMATS}


@pytest.mark.parametrize("fmt", FORMATS)
def test_damaged_logs_are_processed_whole_or_refused_in_one_line(
    fmt: str, clean_logs: dict[str, bytes], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Truncated, bit-flipped, zeroed and randomised copies (seeded): each is either processed with all 62
    frames and exit 0, or refused with exit 2 and one line that names no exception; never a traceback, never a
    shorter map."""
    outcomes: dict[str, int] = {}
    for seed in range(40):
        kind, data = damaged(clean_logs[fmt], seed)
        log = tmp_path / f"damaged-{seed}.{fmt}"
        log.write_bytes(data)
        code, out, err = _run(capsys, "process", str(log), "--preset", "irat", "--json")
        if code == 0:
            assert json.loads(out.strip().splitlines()[-1])["frames"] == 62, (seed, kind)
        else:
            assert code == 2 and out == "", (seed, kind, err)
            line = _error_line(err)
            assert not line.rstrip(".").split(": ")[-1].isdigit(), line  # no bare number as the reason
        key = f"{kind}-{'ok' if code == 0 else 'refused'}"
        outcomes[key] = outcomes.get(key, 0) + 1
        log.unlink()
    assert outcomes.get("truncated-refused", 0) == 10, outcomes  # every truncated copy is refused


def test_library_errors_read_as_their_reason() -> None:
    """A library's argument tuple inside its message is reduced to the text; Python's integer overflow (a damaged
    length field) is malformed data, undecodable text malformed text; a reason of its own is kept."""
    from mapserver.errors import describe_cause

    class ReaderError(Exception):
        pass

    assert describe_cause(ReaderError("Bag index looks damaged: ('Header could not be read from file.',)")) == \
        "Bag index looks damaged: Header could not be read from file."  # fmt: skip
    assert describe_cause(ReaderError("damaged: (\"Record of type 'CHUNK_INFO' is unexpected.\",)")) == \
        "damaged: Record of type 'CHUNK_INFO' is unexpected."  # fmt: skip
    assert describe_cause(OverflowError("Python int too large to convert to C ssize_t")) == "malformed data"
    assert describe_cause(ReaderError("File end magic is invalid.")) == "File end magic is invalid."
    undecodable = UnicodeDecodeError("utf-8", b"\xdc", 0, 1, "invalid continuation byte")
    assert describe_cause(undecodable) == "malformed text (not UTF-8)"


@pytest.mark.parametrize("fmt", FORMATS)
def test_cut_tails_and_damaged_headers_are_refused_in_one_clear_line(
    fmt: str, clean_logs: dict[str, bytes], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The last 1, 64 and 4096 bytes cut (the index, footer or last chunk) and the first bytes inverted: refused,
    exit 2, one line with no exception's name or argument tuple — or, where the damage hit bytes that carry no
    message (a SQLite file's unused tail), processed whole; never a shorter map. ROS 1 and MCAP files end with
    their index or footer: every cut there is refused."""
    refused = []
    data = clean_logs[fmt]
    cases = {f"cut-{n}": data[: len(data) - n] for n in (1, 64, 4096)}
    for at in (0, 4):
        flipped = bytearray(data)
        flipped[at] ^= 0xFF
        cases[f"header-{at}"] = bytes(flipped)
    for name, damaged_bytes in cases.items():
        log = tmp_path / f"{name}.{fmt}"
        log.write_bytes(damaged_bytes)
        code, out, err = _run(capsys, "process", str(log), "--preset", "irat", "--json")
        if code == 0:
            assert json.loads(out.strip().splitlines()[-1])["frames"] == 62, (name, err)
            continue
        assert code == 2 and out == "", (name, err)
        line = _error_line(err)
        assert "('" not in line and "Error" not in line.removeprefix("ERROR"), (name, line)
        refused.append(name)
    if fmt != "db3":
        assert refused == list(cases), refused
    log = tmp_path / f"whole.{fmt}"
    log.write_bytes(data)
    code, out, err = _run(capsys, "process", str(log), "--preset", "irat", "--json")
    assert code == 0 and json.loads(out.strip().splitlines()[-1])["frames"] == 62, err

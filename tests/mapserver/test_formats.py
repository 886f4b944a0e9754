"""Map JSON and TUM formats: exact documents, round trips and error messages."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from core import LinkKind
from mapserver.errors import InputError, MapServerError
from mapserver.formats import (
    LINK_KIND_CODES,
    LINK_KIND_NAMES,
    MAP_FORMAT,
    SessionInfo,
    Trajectory,
    link_kind_name,
    map_json,
    map_trajectory,
    odometry_trajectory,
    read_map_json,
    read_tum,
    write_map_json,
    write_tum,
)

SQRT_HALF = math.sqrt(0.5)


# ----------------------------------------------------------------------------------------------- link kinds


def test_link_kind_names_are_the_engine_enums_names_by_code() -> None:
    assert LINK_KIND_NAMES == ("odometry", "loop", "merge", "manual")  # the map JSON and store contract
    for kind in LinkKind:
        assert LINK_KIND_NAMES[kind] == kind.name.lower() == link_kind_name(int(kind))
        assert LINK_KIND_CODES[kind.name.lower()] == kind
    assert link_kind_name(len(LINK_KIND_NAMES)) is None and link_kind_name(-1) is None


# ----------------------------------------------------------------------------------------------- TUM


def test_tum_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    n = 25
    stamps = 1_600_000_000.0 + np.cumsum(rng.uniform(0.01, 0.2, n))
    positions = rng.normal(0.0, 50.0, (n, 3))
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    path = tmp_path / "traj.tum"
    write_tum(path, stamps, positions, quats)
    lines = path.read_text(encoding="utf-8").splitlines()
    assert lines[0] == "# timestamp x y z qx qy qz qw"
    assert len(lines) == n + 1
    assert lines[1].split()[0] == f"{stamps[0]:.9f}"
    traj = read_tum(path)
    assert len(traj) == n
    np.testing.assert_allclose(traj.stamps_s, stamps, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(traj.positions_xyz, positions)
    np.testing.assert_array_equal(traj.quat_xyzw, quats)
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind


def test_read_tum_comments_blank_lines_and_order(tmp_path: Path) -> None:
    path = tmp_path / "gt.txt"
    path.write_text(
        "# ground truth\n\n2.0 1 2 3 0 0 0 1\n   # indented comment\n1.0\t4 5 6 0 0 1 0\n\n",
        encoding="utf-8",
    )
    traj = read_tum(path)
    np.testing.assert_array_equal(traj.stamps_s, [1.0, 2.0])
    np.testing.assert_array_equal(traj.positions_xyz, [[4, 5, 6], [1, 2, 3]])
    np.testing.assert_array_equal(traj.quat_xyzw, [[0, 0, 1, 0], [0, 0, 0, 1]])


@pytest.mark.parametrize(
    ("bad_line", "reason"),
    [
        ("3.0 1 2 3 0 0 1", "expected 8 fields"),
        ("3.0 1 2 x 0 0 0 1", "not a number"),
        ("3.0 1 2 nan 0 0 0 1", "non-finite"),
    ],
)
def test_read_tum_malformed_line_names_line_number(tmp_path: Path, bad_line: str, reason: str) -> None:
    path = tmp_path / "bad.tum"
    path.write_text(f"# header\n1.0 0 0 0 0 0 0 1\n\n{bad_line}\n5.0 0 0 0 0 0 0 1\n", encoding="utf-8")
    with pytest.raises(InputError, match=reason) as info:
        read_tum(path)
    assert f"{path}:4:" in str(info.value)
    assert "\n" not in str(info.value)


def test_read_tum_missing_and_empty(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        read_tum(tmp_path / "nope.tum")
    empty = tmp_path / "empty.tum"
    empty.write_text("# only a comment\n", encoding="utf-8")
    with pytest.raises(InputError, match="no pose"):
        read_tum(empty)


def test_write_tum_shape_mismatch(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="shapes disagree"):
        write_tum(tmp_path / "x.tum", [0.0, 1.0], np.zeros((2, 3)), np.zeros((3, 4)))


# ----------------------------------------------------------------------------------------------- map JSON


def _tiny_snapshot() -> dict[str, np.ndarray]:
    return {
        "lv_templates": np.zeros((3, 2, 4), dtype=np.float32),
        "lv_means": np.array([0.1, 0.2, 0.3]),
        "em_pose": np.array([[0.0, 0.0, 0.0, 0.0], [1.0, 2.0, 0.5, math.pi / 2]]),
        "em_template": np.array([0, 2], dtype=np.int64),
        "em_stamp": np.array([10.0, 11.5]),
        "em_origin": np.array([7, 8], dtype=np.int64),
        "em_link_from": np.array([0], dtype=np.int64),
        "em_link_to": np.array([1], dtype=np.int64),
        "em_link_transform": np.array([[1.0, 2.0, 0.5, math.pi / 2]]),
        "em_link_dt": np.array([1.5]),
        "em_link_distance": np.array([2.25]),
        "em_link_kind": np.array([1], dtype=np.int8),
    }


def _assert_plain(value: Any) -> None:
    """Every value must be a plain JSON type (no numpy scalars)."""
    if isinstance(value, dict):
        for k, v in value.items():
            assert type(k) is str
            _assert_plain(v)
    elif isinstance(value, list):
        for v in value:
            _assert_plain(v)
    else:
        assert value is None or type(value) in (int, float, str, bool), type(value)


def test_map_json_exact_document() -> None:
    doc = map_json(
        params={"vt_match_threshold": np.float64(0.03), "pc_dim_xy": np.int64(21), "name": "irat"},
        snapshot=_tiny_snapshot(),
        sessions=[SessionInfo("a", "ab" * 32, 120), SessionInfo("b", "cd" * 32, np.int64(80))],
        session_name_by_origin={7: "a", 8: "b"},
    )
    expected = {
        "format": "mapserver-map/1",
        "params": {"vt_match_threshold": 0.03, "pc_dim_xy": 21, "name": "irat"},
        "sessions": [
            {"name": "a", "log_sha256": "ab" * 32, "frames": 120},
            {"name": "b", "log_sha256": "cd" * 32, "frames": 80},
        ],
        "templates": 3,
        "experiences": [
            {
                "id": 0,
                "x": 0.0,
                "y": 0.0,
                "z": 0.0,
                "qx": 0.0,
                "qy": 0.0,
                "qz": 0.0,
                "qw": 1.0,
                "yaw": 0.0,
                "template": 0,
                "stamp": 10.0,
                "session": "a",
            },
            {
                "id": 1,
                "x": 1.0,
                "y": 2.0,
                "z": 0.5,
                "qx": 0.0,
                "qy": 0.0,
                "qz": pytest.approx(SQRT_HALF, abs=1e-15),
                "qw": pytest.approx(SQRT_HALF, abs=1e-15),
                "yaw": math.pi / 2,
                "template": 2,
                "stamp": 11.5,
                "session": "b",
            },
        ],
        "links": [
            {
                "from": 0,
                "to": 1,
                "dt": 1.5,
                "distance": 2.25,
                "kind": "loop",
                "transform": [1.0, 2.0, 0.5, math.pi / 2],
            }
        ],
    }
    assert doc == expected
    _assert_plain(doc)
    json.dumps(doc, allow_nan=False)


def test_map_json_unknown_origin_and_odometry_extension() -> None:
    doc = map_json(
        params={},
        snapshot=_tiny_snapshot(),
        sessions=[],
        session_name_by_origin={7: "a"},
        odometry=np.array([[10.0, 0.0, 0.0, 0.0], [10.5, 0.5, 0.1, 0.0]]),
    )
    assert [e["session"] for e in doc["experiences"]] == ["a", None]
    assert doc["odometry"] == [[10.0, 0.0, 0.0, 0.0], [10.5, 0.5, 0.1, 0.0]]
    odo = odometry_trajectory(doc)
    assert odo is not None
    np.testing.assert_array_equal(odo.positions_xyz, [[0.0, 0.0, 0.0], [0.5, 0.1, 0.0]])
    _assert_plain(doc)


def test_map_json_frames_extension_round_trip(tmp_path: Path) -> None:
    doc = map_json(
        params={}, snapshot=_tiny_snapshot(), sessions=[], session_name_by_origin={},
        frames=[(10.0, 0, True), (10.5, 0, False), (11.0, np.int64(1), np.bool_(True))],
    )
    assert doc["frames"] == [[10.0, 0, 1], [10.5, 0, 0], [11.0, 1, 1]]
    _assert_plain(doc)
    write_map_json(tmp_path / "m.json", doc)
    assert read_map_json(tmp_path / "m.json")["frames"] == doc["frames"]
    with pytest.raises(ValueError, match="frames rows"):
        map_json(params={}, snapshot=_tiny_snapshot(), sessions=[], session_name_by_origin={}, frames=[(1.0, 2)])


def test_map_json_rejects_unknown_link_kind() -> None:
    snap = _tiny_snapshot()
    snap["em_link_kind"] = np.array([9], dtype=np.int8)
    with pytest.raises(ValueError, match="em_link_kind"):
        map_json(params={}, snapshot=snap, sessions=[], session_name_by_origin={})


def _doc() -> dict[str, Any]:
    return map_json(
        params={"a": 1},
        snapshot=_tiny_snapshot(),
        sessions=[SessionInfo("a", "00", 2)],
        session_name_by_origin={7: "a", 8: "a"},
    )


def test_map_json_write_read_round_trip(tmp_path: Path) -> None:
    doc = _doc()
    path = tmp_path / "map.json"
    write_map_json(path, doc)
    assert read_map_json(path) == doc
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.json"]
    traj = map_trajectory(doc)
    np.testing.assert_array_equal(traj.stamps_s, [10.0, 11.5])
    np.testing.assert_array_equal(traj.positions_xyz, [[0, 0, 0], [1, 2, 0.5]])


def test_map_trajectory_sorts_by_stamp() -> None:
    doc = _doc()
    doc["experiences"][0]["stamp"] = 20.0
    traj = map_trajectory(doc)
    np.testing.assert_array_equal(traj.stamps_s, [11.5, 20.0])
    np.testing.assert_array_equal(traj.positions_xyz[0], [1, 2, 0.5])


def test_write_map_json_rejects_nan(tmp_path: Path) -> None:
    doc = _doc()
    doc["experiences"][0]["x"] = float("nan")
    with pytest.raises(MapServerError, match="cannot write map JSON"):
        write_map_json(tmp_path / "map.json", doc)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("mutate", "reason"),
    [
        (lambda d: d.update(format="other/1"), "has format 'other/1'"),
        (lambda d: d.pop("links"), "lacks key"),
        (lambda d: d["experiences"][1].pop("stamp"), r"experiences\[1\] lacks key\(s\) stamp"),
        (lambda d: d["experiences"][0].update(x="1"), r"experiences\[0\]\.x is not a number"),
        (lambda d: d["links"][0].update(to=42), r"links\[0\]\.to = 42 is not an experience id"),
        (lambda d: d.update(experiences={}), "'experiences' is not a list"),
        (lambda d: d.update(frames=[[0.0, 1]]), "'frames' is not a list of \\[stamp, template, created\\]"),
        (lambda d: d.update(frames=[[0.0, "1", 0]]), "'frames' is not a list"),
    ],
)
def test_read_map_json_validation(tmp_path: Path, mutate: Any, reason: str) -> None:
    doc = _doc()
    mutate(doc)
    path = tmp_path / "map.json"
    path.write_text(json.dumps(doc), encoding="utf-8")
    with pytest.raises(InputError, match=reason) as info:
        read_map_json(path)
    assert "\n" not in str(info.value)


def test_read_map_json_unreadable(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        read_map_json(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "mapserver-map/1",\n "params": }', encoding="utf-8")
    with pytest.raises(InputError, match=r"not valid JSON.*line 2"):
        read_map_json(bad)
    nan = tmp_path / "nan.json"
    nan.write_text(json.dumps(_doc()).replace('"x": 0.0', '"x": NaN', 1), encoding="utf-8")
    with pytest.raises(InputError, match="non-finite"):
        read_map_json(nan)
    arr = tmp_path / "arr.json"
    arr.write_text("[]", encoding="utf-8")
    with pytest.raises(InputError, match="not a JSON object"):
        read_map_json(arr)
    assert MAP_FORMAT == "mapserver-map/1"


def test_trajectory_shapes() -> None:
    traj = Trajectory([2.0, 1.0], [[0, 0, 0], [1, 1, 1]], [[0, 0, 0, 1], [0, 0, 0, 1]])
    assert traj.positions_xyz.dtype == np.float64
    s = traj.sorted()
    np.testing.assert_array_equal(s.stamps_s, [1.0, 2.0])
    np.testing.assert_array_equal(s.positions_xyz[0], [1, 1, 1])


# ------------------------------------------------------------------------------ bounds (issue 61, mapserver.bounds)
@pytest.mark.parametrize(
    ("text", "value", "reason"),
    [
        ('"x": 0.0', '"x": 1e400', "number '1e400' is beyond the float range"),  # json reads 1e400 as inf
        ('"x": 0.0', '"x": -1e400', "number '-1e400' is beyond the float range"),
        ('"x": 0.0', '"x": 1e300', r"experiences\[0\]\.x is 1e\+300, beyond ±1e\+08 m"),
        ('"z": 0.0', '"z": -100000000.5', r"experiences\[0\]\.z is -100000000\.5, beyond ±1e\+08 m"),
        ('"yaw": 0.0', '"yaw": 1e7', r"experiences\[0\]\.yaw is 1e\+07, beyond ±1e\+06 rad"),
        ('"stamp": 10.0', '"stamp": 2e10', r"experiences\[0\]\.stamp is 2e\+10, beyond ±1e\+10 s"),
        ('"distance": ', '"distance": 1e300, "was": ', r"links\[0\]\.distance is 1e\+300, beyond ±1e\+08 m"),
    ],
)
def test_read_map_json_refuses_numbers_beyond_the_bounds(tmp_path: Path, text: str, value: str, reason: str) -> None:
    path = tmp_path / "map.json"
    source = json.dumps(_doc())
    assert text in source
    path.write_text(source.replace(text, value, 1), encoding="utf-8")
    with pytest.raises(InputError, match=reason) as info:
        read_map_json(path)
    assert "\n" not in str(info.value)


def test_read_map_json_accepts_numbers_at_the_bounds(tmp_path: Path) -> None:
    doc = _doc()
    doc["experiences"][0].update(x=1e8, y=-1e8, z=1e8, yaw=-1e6, stamp=1e10)
    doc["links"][0].update(dt=1e10, distance=1e8)
    path = tmp_path / "map.json"
    path.write_text(json.dumps(doc), encoding="utf-8")
    assert read_map_json(path)["experiences"][0]["x"] == 1e8


def test_read_tum_refuses_stamps_and_coordinates_beyond_the_bounds(tmp_path: Path) -> None:
    path = tmp_path / "gt.tum"
    for line, reason in (("2e10 0 0 0 0 0 0 1", "timestamp is 2e+10, beyond ±1e+10 s"),
                         ("1.0 0 1e300 0 0 0 0 1", "y is 1e+300, beyond ±1e+08 m"),
                         ("1.0 0 0 1e400 0 0 0 1", "non-finite value")):  # fmt: skip
        path.write_text(f"{line}\n", encoding="utf-8")
        with pytest.raises(InputError) as info:
            read_tum(path)
        assert f"{path}:1: " in str(info.value) and reason in str(info.value)
    path.write_text("1e10 1e8 -1e8 1e8 0 0 0 1\n", encoding="utf-8")
    assert read_tum(path).positions_xyz.tolist() == [[1e8, -1e8, 1e8]]


@pytest.mark.parametrize(("umask", "mode"), [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_written_files_take_the_mode_the_umask_gives(tmp_path: Path, umask: int, mode: int) -> None:
    """Outputs are readable by whom the umask allows (must: 0644 under 022), and no more (must not: 0644 under 077)."""
    import subprocess
    import sys

    script = (
        "import os, sys; os.umask(int(sys.argv[1], 8)); from mapserver.formats import atomic_write_bytes, "
        "atomic_write_chunks; atomic_write_bytes(sys.argv[2] + '/a', b'x'); atomic_write_chunks(sys.argv[2] + '/b', "
        "[b'y'])"
    )
    subprocess.run([sys.executable, "-c", script, oct(umask)[2:], str(tmp_path)], check=True)
    for name in ("a", "b"):
        assert (tmp_path / name).stat().st_mode & 0o777 == mode
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []

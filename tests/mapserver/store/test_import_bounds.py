"""Map imports at the edge (issue 61): non-finite or physically absurd poses, links, times and templates are refused.

``mapserver import`` of a multisession-ratslam save and of a g2o file take the bounds of ``mapserver.bounds``
(the odometry check's): each refusal is one ``ERROR:`` line naming the file, line and field, exit 2, nothing
written, and a SQL check finds nothing non-finite (or beyond the position bound) in the database; each is
paired with the value at its bound, which is imported.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa

from mapserver.bounds import MAX_ANGLE_RAD, MAX_POSITION_M, MAX_TIME_S
from mapserver.cli import main
from mapserver.store import load_map, open_database
from tests.mapserver.hostile import nonfinite_floats
from tests.mapserver.store.test_import import TX, TY, small_params, write_save_dir

Edit = Callable[[Path], None]


def _set_line(file: str, index: int, value: str) -> Edit:
    """Return an edit that replaces line ``index`` (0-based) of ``file`` in a save directory."""

    def edit(directory: Path) -> None:
        path = directory / file
        lines = path.read_text().split("\n")
        lines[index] = value
        path.write_text("\n".join(lines))

    return edit


def _template_value(value: str) -> Edit:
    """Return an edit that sets the sixth value of template 1's data."""

    def edit(directory: Path) -> None:
        path = directory / "localviewcells.txt"
        lines = path.read_text().split("\n")
        data = lines[6].split()
        data[5] = value
        lines[6] = " ".join(data)
        path.write_text("\n".join(lines))

    return edit


def _creation_dts(value: str) -> Edit:
    def edit(directory: Path) -> None:
        for k in range(3):  # the three links that create experiences 1, 2, 3
            _set_line("links.txt", 6 * k + 5, value)(directory)

    return edit


# experiences.txt: experience i on lines 10i .. 10i+9 (id, x_m, y_m, th_rad, vt, from[], to[], t, goal, goal);
# links.txt: link k on lines 6k .. 6k+5 (d, heading, facing, to, from, dt); link 3 is the loop link
REFUSED: dict[str, tuple[Edit, str]] = {
    "x-nan": (_set_line("experiences.txt", 21, "nan"), "experiences.txt:22: x_m is not finite: 'nan'"),
    "x-inf": (_set_line("experiences.txt", 21, "inf"), "x_m is not finite: 'inf'"),
    "x-1e300": (_set_line("experiences.txt", 21, "1e300"), "experiences.txt:22: x_m is 1e+300, beyond ±1e+08 m"),
    "y-beyond": (_set_line("experiences.txt", 22, "-1.5e8"), "y_m is -1.5e+08, beyond ±1e+08 m"),
    "yaw-1e300": (_set_line("experiences.txt", 23, "1e300"), "th_rad is 1e+300, beyond ±1e+06 rad"),
    "link-d": (_set_line("links.txt", 18, "1e300"), "links.txt:19: d is 1e+300, beyond ±1e+08 m"),
    "link-heading": (_set_line("links.txt", 19, "-inf"), "heading_rad is not finite: '-inf'"),
    "link-facing": (_set_line("links.txt", 20, "2e6"), "facing_rad is 2e+06, beyond ±1e+06 rad"),
    "dt-negative": (_set_line("links.txt", 23, "-1"), "links.txt:24: delta_time_s is -1, below 0 s"),
    "dt-1e300": (_set_line("links.txt", 23, "1e300"), "delta_time_s is 1e+300, beyond ±1e+10 s"),
    "stamps": (_creation_dts("6e9"), "delta_time_s add up to a stamp of experience 2 that is 1.2e+10, beyond"),
    "template": (_template_value("1e300"), "localviewcells.txt:7: template data[5] is 1e+300, beyond ±1e+06"),
    "mean": (_set_line("localviewcells.txt", 5, "nan"), "template mean is not finite: 'nan'"),
}


def _config(tmp_path: Path) -> Path:
    config = tmp_path / "params.yaml"
    values = small_params().replace(template_x_size=TX, template_y_size=TY).to_dict()
    config.write_text("".join(f"{k}: {v}\n" for k, v in values.items()))
    return config


def _import(tmp_path: Path, db_url: str, directory: Path, name: str) -> int:
    argv = ["import", str(directory), "--db", db_url, "--format", "multisession-ratslam", "--map", name,
            "--config", str(_config(tmp_path))]  # fmt: skip
    return main(argv)


def _largest_coordinate(db_url: str) -> float:
    """Return the largest |x|, |y|, |z| of the stored experiences and |dx|, |dy| of the links (SQL)."""
    engine = sa.create_engine(db_url)
    try:
        with engine.connect() as conn:
            poses = conn.execute(sa.text("SELECT MAX(ABS(x)), MAX(ABS(y)), MAX(ABS(z)) FROM experiences")).one()
            links = conn.execute(sa.text("SELECT MAX(ABS(dx)), MAX(ABS(dy)), MAX(ABS(dt)) FROM links")).one()
    finally:
        engine.dispose()
    return max(float(v or 0.0) for v in (*poses, *links))


def _error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ERROR: "), err
    assert "Traceback" not in err and "Error" not in lines[0].removeprefix("ERROR: "), err
    return lines[0]


@pytest.mark.parametrize("case", list(REFUSED))
def test_a_save_with_a_bad_value_is_refused_in_one_line_and_nothing_is_stored(
    case: str, tmp_path: Path, db_url: str, capsys: pytest.CaptureFixture[str]
) -> None:
    edit, message = REFUSED[case]
    directory = write_save_dir(tmp_path / "save")
    edit(directory)
    capsys.readouterr()
    assert _import(tmp_path, db_url, directory, "bad") == 2
    assert message in _error_line(capsys.readouterr().err)
    with open_database(db_url) as db, db.read() as conn:
        assert conn.execute(sa.text("SELECT COUNT(*) FROM maps")).scalar_one() == 0
    assert nonfinite_floats(db_url) == {}


def test_a_save_at_every_bound_is_imported_and_stored_finite(
    tmp_path: Path, db_url: str, capsys: pytest.CaptureFixture[str]
) -> None:
    directory = write_save_dir(tmp_path / "save")
    for edit in (
        _set_line("experiences.txt", 21, repr(MAX_POSITION_M)),
        _set_line("experiences.txt", 22, repr(-MAX_POSITION_M)),
        _set_line("experiences.txt", 23, repr(-MAX_ANGLE_RAD)),
        _set_line("links.txt", 18, repr(MAX_POSITION_M)),
        _set_line("links.txt", 20, repr(MAX_ANGLE_RAD)),
        _set_line("links.txt", 23, repr(MAX_TIME_S)),  # the loop link: no stamp is built from it
        _set_line("links.txt", 5, "0"),
        _template_value("1e6"),
    ):
        edit(directory)
    assert _import(tmp_path, db_url, directory, "edge") == 0, capsys.readouterr().err
    with open_database(db_url) as db:
        pose = load_map(db, name="edge").snapshot["em_pose"]
    assert pose[2].tolist() == [MAX_POSITION_M, -MAX_POSITION_M, 0.0, -MAX_ANGLE_RAD]
    assert nonfinite_floats(db_url) == {}
    assert _largest_coordinate(db_url) == MAX_TIME_S  # the loop link's dt; every coordinate within 1e8


# ------------------------------------------------------------------------------------------------- g2o
def _stored(tmp_path: Path, db_url: str) -> Path:
    """Import the hand-written save as map 'm' and export it as g2o; return the file."""
    assert _import(tmp_path, db_url, write_save_dir(tmp_path / "save"), "m") == 0
    out = tmp_path / "m.g2o"
    assert main(["export", "--db", db_url, "--map", "m", "--format", "g2o", "--out", str(out)]) == 0
    return out


def _vertex_2(text: str, values: str, tag: str = "VERTEX_SE2") -> str:
    lines = [f"{tag} 2 {values}" if line.startswith("VERTEX_SE2 2 ") else line for line in text.splitlines()]
    return "\n".join(lines) + "\n"


def _se3(values: str) -> str:
    return "".join(f"VERTEX_SE3:QUAT {i} {values if i == 2 else '0 0 0 0 0 0 1'}\n" for i in range(4))


G2O_REFUSED: dict[str, tuple[Callable[[str], str], str]] = {
    "x-nan": (lambda t: _vertex_2(t, "nan 0.5 0.3"), "VERTEX_SE2 holds a non-finite value"),
    "x-1e300": (lambda t: _vertex_2(t, "1e300 0.5 0.3"), "VERTEX_SE2 x is 1e+300, beyond ±1e+08 m"),
    "y-beyond": (lambda t: _vertex_2(t, "0 -2e8 0.3"), "VERTEX_SE2 y is -2e+08, beyond ±1e+08 m"),
    "theta": (lambda t: _vertex_2(t, "0 0 1e300"), "VERTEX_SE2 theta is 1e+300, beyond ±1e+06 rad"),
    "se3-z": (lambda _t: _se3("0 0 1e300 0 0 0 1"), "VERTEX_SE3:QUAT z is 1e+300, beyond ±1e+08 m"),
    "se3-inf": (lambda _t: _se3("0 0 0 0 0 inf 1"), "VERTEX_SE3:QUAT holds a non-finite value"),
}


@pytest.mark.parametrize("case", list(G2O_REFUSED))
def test_g2o_poses_with_a_bad_value_are_refused_and_the_map_is_kept(
    case: str, tmp_path: Path, db_url: str, capsys: pytest.CaptureFixture[str]
) -> None:
    edit, message = G2O_REFUSED[case]
    exported = _stored(tmp_path, db_url)
    bad = tmp_path / "bad.g2o"
    bad.write_text(edit(exported.read_text()))
    with open_database(db_url) as db:
        before = load_map(db, name="m")
    capsys.readouterr()
    assert main(["import", str(bad), "--db", db_url, "--format", "g2o", "--map", "m"]) == 2
    line = _error_line(capsys.readouterr().err)
    assert f"{bad}:3: {message}" in line
    with open_database(db_url) as db:
        after = load_map(db, name="m")
    assert after.meta.map.version == before.meta.map.version
    assert np.array_equal(after.snapshot["em_pose"], before.snapshot["em_pose"])
    assert nonfinite_floats(db_url) == {}
    assert _largest_coordinate(db_url) < 10.0


def test_g2o_poses_at_the_bounds_and_huge_quaternions_are_imported(
    tmp_path: Path, db_url: str, capsys: pytest.CaptureFixture[str]
) -> None:
    exported = _stored(tmp_path, db_url)
    edge = tmp_path / "edge.g2o"
    edge.write_text(_vertex_2(exported.read_text(), f"{MAX_POSITION_M!r} {-MAX_POSITION_M!r} {MAX_ANGLE_RAD!r}"))
    assert main(["import", str(edge), "--db", db_url, "--format", "g2o", "--map", "m"]) == 0, capsys.readouterr()
    with open_database(db_url) as db:
        assert load_map(db, name="m").snapshot["em_pose"][2].tolist() == [MAX_POSITION_M, -MAX_POSITION_M, 0.0,
                                                                           MAX_ANGLE_RAD]  # fmt: skip
    # a quaternion is only normalised: components of 1e300 are a rotation (here 90° about z), not an overflow
    se3 = tmp_path / "se3.g2o"
    se3.write_text(_se3(f"{MAX_POSITION_M!r} 0 {-MAX_POSITION_M!r} 0 0 1e300 1e300"))
    assert main(["import", str(se3), "--db", db_url, "--format", "g2o", "--map", "m"]) == 0, capsys.readouterr()
    with open_database(db_url) as db:
        pose = load_map(db, name="m").snapshot["em_pose"][2]
    assert pose[:3].tolist() == [MAX_POSITION_M, 0.0, -MAX_POSITION_M]
    assert pose[3] == pytest.approx(np.pi / 2)
    assert nonfinite_floats(db_url) == {}
    assert _largest_coordinate(db_url) == MAX_POSITION_M

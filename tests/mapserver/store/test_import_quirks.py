"""multisession-ratslam saves as that tool really writes them (each quirk seen in its repository's ``Saves/``).

Every test edits the hand-written save of ``test_import.py`` into the quirk's layout and checks the import
against the plain layout (same snapshot) or against the values written; each accepted quirk is paired with
a malformed variant that must still be refused.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from mapserver.cli import main
from mapserver.errors import InputError
from mapserver.store.import_msr import read_multisession_ratslam
from tests.mapserver.store.test_import import TX, TY, _params, write_save_dir

ID_FILES = ("localviewcells.txt", "posecellvisual_templates.txt", "posecellexperiences.txt", "experiences.txt")


def _snapshot(directory: Path) -> dict[str, np.ndarray]:
    return read_multisession_ratslam(directory, _params()).snapshot


def _same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k], equal_nan=True) for k in a)


def _edit(path: Path, edit) -> None:  # type: ignore[no-untyped-def]
    path.write_text(edit(path.read_text()))


def test_float_ids_such_as_16_0_read_as_integers(tmp_path: Path) -> None:
    plain = _snapshot(write_save_dir(tmp_path / "plain"))
    floats = write_save_dir(tmp_path / "floats")
    # every line that is a bare integer (ids, trailers, TEMPLATE_SIZE) becomes "N.0", as a re-saved map has them
    for name in (*ID_FILES, "links.txt"):
        _edit(floats / name, lambda t: re.sub(r"(?m)^(-?\d+)$", r"\1.0", t))
    assert "\n3.0\n2.0\n" in (floats / "experiences.txt").read_text()  # the edit reached the trailer
    assert _same(_snapshot(floats), plain)
    # a fractional id is still refused
    _edit(floats / "experiences.txt", lambda t: t.replace("\n-\n3.0\n", "\n-\n2.5\n"))
    with pytest.raises(InputError, match=r"the current id after '-' is not an integer: 2\.5"):
        _snapshot(floats)


def test_scientific_notation_is_read_exactly(tmp_path: Path) -> None:
    directory = write_save_dir(tmp_path / "sci")
    # the tool writes str(float) (1.38777878078e-17) and numpy's %.18e (0.000000000000000000e+00)
    _edit(directory / "experiences.txt", lambda t: t.replace("\n6.9e-18\n", "\n1.38777878078e-17\n", 1))
    _edit(directory / "links.txt", lambda t: t.replace("3.0\n", "3.000000000000000000e+00\n", 1))
    snap = _snapshot(directory)
    assert snap["em_pose"][0, 1] == 1.38777878078e-17
    assert snap["em_link_dt"][0] == 3.0
    _edit(directory / "links.txt", lambda t: t.replace("3.000000000000000000e+00\n", "3.0e+0.5\n", 1))
    with pytest.raises(InputError, match=r"delta_time_s is not a number: '3\.0e"):
        _snapshot(directory)


def test_an_empty_previous_id_is_none(tmp_path: Path) -> None:
    # a map loaded and saved again by the tool ends posecellvisual_templates.txt with "-", current, ""
    directory = write_save_dir(tmp_path / "resaved")
    path = directory / "posecellvisual_templates.txt"
    _edit(path, lambda t: t.replace("\n-\n1\n2\n", "\n-\n16.0\n\n"))
    assert path.read_text().endswith("-\n16.0\n\n")
    snap = _snapshot(directory)
    assert int(snap["pc_current_vt"]) == -1  # 16 names no template of this 3-template map
    _edit(path, lambda t: t.replace("\n-\n16.0\n\n", "\n-\n1\n\n"))
    snap = _snapshot(directory)
    assert (int(snap["pc_current_vt"]), int(snap["pc_prev_vt"])) == (1, -1)
    # the trailer may also simply stop after the current id
    _edit(path, lambda t: t.replace("\n-\n1\n\n", "\n-\n1\n"))
    assert (int(_snapshot(directory)["pc_prev_vt"])) == -1
    # but a previous id that is there must be a number, and nothing but blank lines may follow it
    _edit(path, lambda t: t.replace("\n-\n1\n", "\n-\n1\nx\n"))
    with pytest.raises(InputError, match="the previous id after '-' is not a number: 'x'"):
        _snapshot(directory)
    _edit(path, lambda t: t.replace("\n-\n1\nx\n", "\n-\n1\n2\n\n7\n"))
    with pytest.raises(InputError, match="unexpected lines after the current and previous ids"):
        _snapshot(directory)


def test_blank_lines_are_empty_lists(tmp_path: Path) -> None:
    directory = write_save_dir(tmp_path / "lists")
    text = (directory / "experiences.txt").read_text().split("\n")
    assert text[6] == ""  # experience 0's links_to: no link reaches the first experience
    assert (directory / "posecellvisual_templates.txt").read_text().split("\n")[17] == ""  # template 2: no exps
    snap = _snapshot(directory)
    assert snap["em_pose"].shape[0] == 4 and snap["pc_link_template"].shape[0] == 3
    # a blank line where a number belongs is still refused
    _edit(directory / "experiences.txt", lambda t: t.replace("\n0.1\n", "\n\n", 1))
    with pytest.raises(InputError, match="th_rad is not a number: ''"):
        _snapshot(directory)


def test_goal_list_may_be_empty_or_absent(tmp_path: Path) -> None:
    directory = write_save_dir(tmp_path / "goals")
    assert (directory / "goal_list.txt").read_text() == ""
    plain = _snapshot(directory)
    (directory / "goal_list.txt").unlink()
    assert _same(_snapshot(directory), plain)
    (directory / "goal_list.txt").write_text("3.000000000000000000e+00 ")  # goals are not part of a map
    assert _same(_snapshot(directory), plain)


def _write_unstarted(directory: Path, *, all_empty: bool) -> Path:
    """A map the tool saved before its first frame (or, ``all_empty``, a directory of empty files)."""
    directory.mkdir(parents=True)
    files = {
        "localviewcells.txt": f"{TX * TY}\n-\n0\n0\n",
        "posecellvisual_templates.txt": "",
        "posecellexperiences.txt": "-\n0\n0\n",
        "experiences.txt": "-\n0\n0\n",
        "links.txt": "",
        "goal_list.txt": "",
    }
    for name, text in files.items():
        (directory / name).write_text("" if all_empty else text)
    return directory


@pytest.mark.parametrize("all_empty", [False, True])
def test_a_map_saved_before_its_first_frame_imports_empty(tmp_path: Path, db_url: str, capsys, all_empty) -> None:  # type: ignore[no-untyped-def]
    directory = _write_unstarted(tmp_path / "unstarted", all_empty=all_empty)
    snap = _snapshot(directory)
    assert snap["lv_templates"].shape == (0, TY, TX) and snap["em_pose"].shape == (0, 4)
    assert snap["em_link_from"].shape == (0,)
    # the tool's initial current ids (0) name no record: none
    assert [int(snap[k]) for k in ("lv_current", "pc_current_vt", "em_current")] == [-1, -1, -1]
    config = tmp_path / "params.yaml"
    config.write_text("".join(f"{k}: {v}\n" for k, v in _params().to_dict().items()))
    code = main(["import", str(directory), "--db", db_url, "--format", "multisession-ratslam", "--map", "empty",
                 "--config", str(config), "--json"])  # fmt: skip
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert json.loads(captured.out.splitlines()[-1])["experiences"] == 0
    # once it has records, a current id outside them is an error again
    if not all_empty:
        _edit(directory / "experiences.txt", lambda t: "0\n0.0\n0.0\n0.0\n0\n\n\n0\n-1\n-1\n-\n4\n0\n")
        _edit(directory / "posecellexperiences.txt", lambda t: "1\n1\n1\n0\n-\n0\n0\n")
        _edit(directory / "localviewcells.txt", lambda t: f"{TX * TY}\n0\n0.5\n{'0.5 ' * (TX * TY)}\n-\n0\n0\n")
        _edit(directory / "posecellvisual_templates.txt", lambda t: "0\n1\n1\n1\n0.0\n0\n-\n0\n0\n")
        with pytest.raises(InputError, match=r"the current experience 4 is not one of 0\.\.0"):
            _snapshot(directory)

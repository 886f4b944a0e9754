"""Import of the multisession-ratslam save directory (files written here by hand in that format)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from core import Engine, Params
from mapserver.cli import main
from mapserver.errors import InputError
from mapserver.store import load_map, open_database
from mapserver.store.import_msr import read_multisession_ratslam
from tests.mapserver.store.conftest import small_params

TX, TY = 12, 2
LINKS = [  # d, heading, facing, to, from, dt
    (1.0, 0.0, 0.1, 1, 0, 3.0),
    (1.25, 0.3, 0.2, 2, 1, 2.0),
    (1.2, 2.5, -0.2, 3, 2, 1.5),
    (0.1, 1.0, 0.0, 1, 3, 0.5),
]


def _params() -> Params:
    return small_params().replace(template_x_size=TX, template_y_size=TY)


def _template(k: int) -> np.ndarray:
    return np.round(np.linspace(0.05, 0.95, TX * TY) ** (k + 1), 6)


def _vector(values) -> str:  # type: ignore[no-untyped-def]
    return "".join(f"{v:.18e} " for v in values)


def write_save_dir(directory: Path) -> Path:
    """A 3-template, 4-experience, 4-link map in multisession-ratslam's save format."""
    directory.mkdir(parents=True, exist_ok=True)
    lvc = [str(TX * TY)]
    for k in range(3):
        lvc += [str(k), repr(float(_template(k).mean())), " ".join(f"{v:.18e}" for v in _template(k)) + " "]
    lvc += ["-", "2", "1"]
    (directory / "localviewcells.txt").write_text("\n".join(lvc) + "\n")
    pcvt = ["0", "5", "5", "18", "1.5", _vector([0]),
            "1", "5.5", "5.25", "19.0", "0.7", _vector([1, 3]),
            "2", "12.0", "5.0", "20.0", "0.0", "",
            "-", "1", "2"]  # fmt: skip
    (directory / "posecellvisual_templates.txt").write_text("\n".join(pcvt) + "\n")
    pcexp = ["5", "5", "18", "0", "5.5", "5.25", "19", "1", "6", "5", "20", "2",
             "5.5", "5.25", "19", "1", "-", "3", "2"]  # fmt: skip
    (directory / "posecellexperiences.txt").write_text("\n".join(pcexp) + "\n")
    poses = [(0.0, 6.9e-18, 0.0, 0), (1.0, 0.0, 0.1, 1), (2.0, 0.5, 0.3, 2), (1.0, 0.1, 0.1, 1)]
    exps: list[str] = []
    for i, (x, y, th, vt) in enumerate(poses):
        links_to = _vector([i - 1] if i else [])
        exps += [str(i), repr(x), repr(y), repr(th), str(vt), _vector([i]), links_to, "0", "-1", "-1"]
    exps += ["-", "3", "2"]
    (directory / "experiences.txt").write_text("\n".join(exps) + "\n")
    links = [repr(float(v)) if j not in (3, 4) else str(v) for row in LINKS for j, v in enumerate(row)]
    (directory / "links.txt").write_text("\n".join(links) + "\n")
    (directory / "goal_list.txt").write_text("")
    return directory


def test_the_format_is_read_into_an_engine_snapshot(tmp_path: Path) -> None:
    params = _params()
    imported = read_multisession_ratslam(write_save_dir(tmp_path / "circle_partial"), params)
    snap = imported.snapshot
    assert snap["lv_templates"].shape == (3, TY, TX) and snap["lv_templates"].dtype == np.float32
    assert np.array_equal(snap["lv_templates"][2].reshape(-1), _template(2).astype(np.float32))
    assert snap["lv_means"][1] == float(_template(1).mean())
    assert (int(snap["lv_current"]), int(snap["lv_previous"])) == (2, 1)
    assert snap["pc_link_template"].tolist() == [0, 1, 2]
    assert snap["pc_link_coords"].tolist() == [[5, 5, 18], [5.5, 5.25, 19], [1.0, 5.0, 20.0]]  # 12 wraps to 1
    assert snap["pc_link_decay"].tolist() == [1.5, 0.7, 0.0] and snap["pc_link_strength"].tolist() == [1, 1, 1]
    assert snap["em_pose"][:, [0, 1, 3]].tolist() == [[0.0, 6.9e-18, 0.0], [1.0, 0.0, 0.1], [2.0, 0.5, 0.3],
                                                     [1.0, 0.1, 0.1]]  # fmt: skip
    assert snap["em_template"].tolist() == [0, 1, 2, 1]
    assert snap["em_stamp"].tolist() == [0.0, 3.0, 5.0, 6.5]  # creation chain of Δt
    assert snap["em_link_from"].tolist() == [0, 1, 2, 3] and snap["em_link_to"].tolist() == [1, 2, 3, 1]
    assert snap["em_link_kind"].tolist() == [0, 0, 0, 1]  # the last link reaches an old experience: a loop
    d, h, f = 1.2, 2.5, -0.2
    assert snap["em_link_transform"][2].tolist() == [d * math.cos(h), d * math.sin(h), 0.0, f]
    assert snap["em_link_dt"].tolist() == [3.0, 2.0, 1.5, 0.5]
    assert (int(snap["em_current"]), int(snap["em_previous"])) == (3, 2)
    assert snap["em_accum"].tolist() == [0.0, 0.0, 0.0, 0.1, 0.0, 0.0]
    # the activity is a fresh engine's packet moved to the current experience's cell (5.5, 5.25, 19) → (6, 5, 19)
    fresh = Engine(params).snapshot()["pc_activity"]
    peak = np.unravel_index(np.argmax(fresh), fresh.shape)
    assert np.array_equal(snap["pc_activity"], np.roll(fresh, (6 - peak[0], 5 - peak[1], 19 - peak[2]), (0, 1, 2)))
    assert snap["pc_best"].tolist() == [6.0, 5.0, 19.0]
    assert any("pose-cell activity is not in this format" in n for n in imported.notes)


def test_cli_import_stores_a_map_that_the_engine_continues(tmp_path: Path, db_url: str, capsys) -> None:  # type: ignore[no-untyped-def]
    directory = write_save_dir(tmp_path / "saved")
    config = tmp_path / "params.yaml"
    config.write_text(f"template_x_size: {TX}\ntemplate_y_size: {TY}\n" + "".join(
        f"{k}: {v}\n" for k, v in small_params().to_dict().items() if k not in ("template_x_size", "template_y_size")
    ))  # fmt: skip
    code = main(["import", str(directory), "--db", db_url, "--format", "multisession-ratslam", "--map", "old",
                 "--config", str(config), "--json"])  # fmt: skip
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert json.loads(captured.out.splitlines()[-1]) | {"notes": None} == {
        "map": "old", "templates": 3, "experiences": 4, "links": 4, "notes": None
    }  # fmt: skip
    assert "note: the pose-cell activity is not in this format" in captured.err
    with open_database(db_url) as db:
        content = load_map(db, name="old")
    engine = Engine.restore(_params(), content.snapshot, origin=content.meta.sessions[0].id)
    image = (np.indices((24, 64)).sum(axis=0) % 200).astype(np.uint8)
    engine.step(image, None, 7.0)
    assert engine.frames == 1 and engine.template_count >= 3
    # a second import of the same directory, or into a taken name, is refused
    assert main(["import", str(directory), "--db", db_url, "--format", "multisession-ratslam", "--map", "again",
                 "--config", str(config)]) == 2  # fmt: skip
    assert "was imported already as session 'old'" in capsys.readouterr().err
    assert main(["import", str(directory), "--db", db_url, "--format", "multisession-ratslam", "--map", "old",
                 "--config", str(config)]) == 2  # fmt: skip
    assert "a map named 'old' already exists" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("file", "edit", "message"),
    [
        ("links.txt", lambda t: t.replace("1.5\n", "abc\n", 1), "links.txt:18: delta_time_s is not a number: 'abc'"),
        ("experiences.txt", lambda t: t.replace("\n-\n3\n", "\n-\n9\n"), "the current experience 9 is not one of 0..3"),
        ("localviewcells.txt", lambda t: t.replace("24\n", "25\n", 1), "templates have 25 values but the parameters"),
        ("posecellexperiences.txt", lambda t: t.replace("\n1\n-", "\n2\n-"), "experience 3 has template 1 in"),
        ("links.txt", lambda t: t + "1.0\n", "is not a whole number of 6-line links"),
        ("posecellvisual_templates.txt", None, "lacks 'posecellvisual_templates.txt'"),
    ],
)
def test_malformed_directories_are_one_line_errors(tmp_path: Path, file: str, edit, message: str) -> None:  # type: ignore[no-untyped-def]
    directory = write_save_dir(tmp_path / "bad")
    path = directory / file
    if edit is None:
        path.unlink()
    else:
        path.write_text(edit(path.read_text()))
    with pytest.raises(InputError) as info:
        read_multisession_ratslam(directory, _params())
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_an_imported_map_keeps_its_saved_poses_unless_asked_to_settle(tmp_path: Path) -> None:
    """The save's poses (hand-written above) are stored as they are; ``--settle`` stores the fixed point instead."""
    directory = write_save_dir(tmp_path / "saved")
    config = tmp_path / "params.yaml"
    config.write_text(f"template_x_size: {TX}\ntemplate_y_size: {TY}\nexp_robust: 0\n")
    kept_url, settled_url = f"sqlite:///{tmp_path / 'kept.db'}", f"sqlite:///{tmp_path / 'settled.db'}"
    for url, extra in ((kept_url, []), (settled_url, ["--settle"])):
        argv = ["import", str(directory), "--db", url, "--format", "multisession-ratslam", "--map", "old",
                "--config", str(config), *extra]  # fmt: skip
        assert main(argv) == 0
    with open_database(kept_url) as db:
        kept = load_map(db, name="old").snapshot
    with open_database(settled_url) as db:
        settled = load_map(db, name="old").snapshot
    saved = read_multisession_ratslam(directory, Params(template_x_size=TX, template_y_size=TY, exp_robust=False))
    np.testing.assert_array_equal(kept["em_pose"], saved.snapshot["em_pose"])  # must not move
    # must move: link 3 → 1 (0.1 m at heading 1.0 from experience 3) contradicts the saved poses, so the fixed
    # point of relaxation over the four links (computed here by the engine on the saved snapshot) differs
    engine = Engine.restore(Params(template_x_size=TX, template_y_size=TY, exp_robust=False), saved.snapshot)
    engine.settle()
    np.testing.assert_allclose(settled["em_pose"], engine.snapshot()["em_pose"], atol=1e-12)
    assert np.abs(settled["em_pose"] - kept["em_pose"]).max() > 0.01

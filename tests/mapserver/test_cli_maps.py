"""``mapserver maps delete|restore|rename``, ``maps --archived`` and ``process --into``: results and exit codes."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from mapserver.cli import main
from tests.mapserver.api.logs import write_strip_log
from tests.mapserver.api.test_map_lifecycle import _store


def _json(capsys: Any, argv: list[str]) -> tuple[int, Any, str]:
    code = main(argv)
    captured = capsys.readouterr()
    lines = captured.out.strip().splitlines()
    return code, json.loads(lines[-1]) if lines and lines[-1].startswith("{") else None, captured.err


def test_delete_restore_rename_purge_from_the_command_line(tmp_path: Path, capsys: Any) -> None:
    db = f"sqlite:///{tmp_path / 'cli.db'}"
    _store(db, "lab", 3)
    _store(db, "yard", 5)
    code, out, _ = _json(capsys, ["maps", "delete", "lab", "--db", db, "--json"])
    assert code == 0 and out["deleted"] == "lab" and out["restorable"] is True
    assert [m["name"] for m in _json(capsys, ["maps", "--db", db, "--json"])[1]["maps"]] == ["yard"]
    archived = _json(capsys, ["maps", "--archived", "--db", db, "--json"])[1]["maps"]
    assert [(m["name"], m["sessions"]) for m in archived] == [("lab", 1)] and archived[0]["archived_at"]
    # refusals: one ERROR line; an unknown map or a bad name is exit 2, a conflict exit 1
    for argv, code_wanted, message in (
        (["maps", "delete", "lab"], 1, "archived already"),
        (["maps", "rename", "lab", "lab2"], 1, "restore it before you rename it"),
        (["maps", "restore", "nope"], 2, "no map named 'nope'"),
        (["maps", "rename", "yard", "a/b"], 2, "invalid map name 'a/b'"),
        (["maps", "delete", "yard", "--purge"], 1, "not archived; delete it first"),
    ):
        code, _, err = _json(capsys, [*argv, "--db", db])
        assert code == code_wanted and message in err and err.count("ERROR:") == 1, (argv, err)
    assert _json(capsys, ["maps", "--db", db, "restore", "lab", "--json"])[:2] == (0, {"restored": "lab"})
    code, out, _ = _json(capsys, ["maps", "rename", "lab", "lab2", "--db", db, "--json"])
    assert (code, out) == (0, {"renamed": "lab", "name": "lab2"})
    assert [m["name"] for m in _json(capsys, ["maps", "--db", db, "--json"])[1]["maps"]] == ["lab2", "yard"]
    assert main(["maps", "delete", "yard", "--db", db]) == 0
    code, out, _ = _json(capsys, ["maps", "delete", "yard", "--purge", "--db", db, "--json"])
    assert (code, out) == (0, {"purged": "yard", "sessions": 1, "merge_events": 0})
    assert _json(capsys, ["maps", "--archived", "--db", db, "--json"])[1] == {"maps": []}
    # an atlas whose maps are all deleted is not empty: the demo is not built over it
    assert main(["maps", "delete", "lab2", "--db", db]) == 0
    assert _json(capsys, ["demo", "--if-empty", "--db", db, "--json"])[:2] == (0, {"built": False, "maps": []})


def test_process_into_refuses_what_it_excludes_and_a_missing_map(tmp_path: Path, capsys: Any) -> None:
    db = f"sqlite:///{tmp_path / 'cli.db'}"
    _store(db, "lab", 3)
    log = write_strip_log(tmp_path / "walk.bag", laps=0.4, seed=4)
    for extra, message in (
        (["--map", "x"], "--into excludes --map"),
        (["--no-merge"], "--into excludes --no-merge"),
        (["--stop-after", "3"], "--into excludes --stop-after"),
    ):
        assert main(["process", str(log), "--preset", "irat", "--db", db, "--into", "lab", *extra]) == 2
        assert message in capsys.readouterr().err
    assert main(["process", str(log), "--preset", "irat", "--db", db, "--into", "nope"]) == 2
    assert "map 'nope' cannot take this session: there is no live map of that name" in capsys.readouterr().err
    assert main(["process", str(log), "--preset", "irat", "--into", "lab"]) == 2
    assert "--into needs --db" in capsys.readouterr().err

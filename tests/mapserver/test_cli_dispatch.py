"""The CLI dispatcher: every command is listed, and running one imports only that command's module."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from mapserver.cli import build_parser, command_modules, main


def test_help_lists_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    for name in command_modules():
        assert name.rstrip("_").replace("_", "-") in out  # import_ registers "import", ground_truth "ground-truth"
    assert len(command_modules()) >= 14


def test_unknown_command_is_an_error_naming_the_choices(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["processs"])
    assert exit_info.value.code == 2
    assert "invalid choice: 'processs'" in capsys.readouterr().err


def test_a_command_parses_the_same_alone_as_in_the_full_parser(tmp_path: Path) -> None:
    argv = ["-v", "maps", "--db", f"sqlite:///{tmp_path / 'x.db'}", "--json"]
    alone = vars(build_parser("maps").parse_args(argv))
    full = vars(build_parser().parse_args(argv))
    assert alone == full


def test_running_a_command_imports_only_its_module(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'x.db'}"
    code = (
        "import sys, json; from mapserver.cli import main; "
        f"rc = main(['maps', '--db', {url!r}, '--json']); "
        "print(json.dumps({'rc': rc, 'modules': sorted(m for m in sys.modules if m.startswith('mapserver.cli.')), "
        "'fastapi': 'fastapi' in sys.modules}))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["rc"] == 0
    assert report["modules"] == ["mapserver.cli._output", "mapserver.cli.maps"]
    assert report["fastapi"] is False  # the server's stack is not loaded to list maps


def test_the_engines_config_error_is_exit_2_in_one_line_and_a_store_error_exit_1(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """core.config.ConfigError is the one ConfigError: the dispatcher maps it to an input error's exit 2."""
    import mapserver.errors
    from core.config import ConfigError
    from mapserver.cli import exit_code
    from mapserver.errors import StoreError

    assert not hasattr(mapserver.errors, "ConfigError")
    code = main(["worker", "--db", "sqlite:///x.db"])  # the worker refuses a database it cannot share
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("ERROR: mapserver worker needs a PostgreSQL database") and err.count("\n") == 1
    assert exit_code(ConfigError("bad")) == 2 and exit_code(StoreError("down")) == 1

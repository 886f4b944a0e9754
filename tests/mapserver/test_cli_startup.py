"""``mapserver process`` start-up: what a command loads before it has work for it (a fresh interpreter each)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mapserver.ingest.writer import write_log
from tests.mapserver.ingest.conftest import arc_odometry, frame_images, identity_gt, test_image

REPO = Path(__file__).resolve().parents[2]
HEAVY = ("scipy", "numba", "rosbags", "cv2", "core.engine", "sqlalchemy", "fastapi", "torch")


def _modules_after(*argv: str) -> set[str]:
    """Run ``mapserver ARGV`` in a fresh interpreter; return the top-level and ``core.*`` modules it loaded."""
    code = (
        "import sys, json\n"
        "from mapserver.cli import main\n"
        "try:\n"
        f"    code = main({list(argv)!r})\n"
        "except SystemExit as done:\n"
        "    code = done.code\n"
        "names = {m for m in sys.modules if '.' not in m or m.startswith('core.')}\n"
        "print(json.dumps(sorted(names)), file=sys.stderr)\n"
        "sys.exit(code)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, env=env, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    return set(json.loads(done.stderr.strip().splitlines()[-1]))


def test_process_help_loads_neither_the_engine_nor_the_reader() -> None:
    loaded = _modules_after("process", "--help")
    assert not loaded & set(HEAVY), sorted(loaded & set(HEAVY))
    assert "core.config" in loaded  # the presets, for the help text


@pytest.mark.parametrize(("frames", "numba"), [(1, False), (300, True)])
def test_only_a_long_log_loads_the_compiled_kernels(tmp_path: Path, frames: int, numba: bool) -> None:
    """numba's ~0.5 s is paid by a log long enough to repay it (core.posecells.worth_compiling), not by one frame."""
    odometry = arc_odometry(2 * frames + 1, 20.0, v=0.5, w=0.2)
    stamps = [stamp for stamp, _ in frame_images(frames, 10.0, False)]
    images = [(stamp, test_image(i, False, (48, 128))) for i, stamp in enumerate(stamps)]
    log = write_log(tmp_path / "mission", "bag", images, odometry, identity_gt(odometry))
    loaded = _modules_after("process", str(log), "--preset", "irat", "--out", str(tmp_path / "map.json"))
    assert ("numba" in loaded) == numba
    assert {"core.engine", "rosbags", "scipy"} <= loaded  # the run itself


def test_the_progress_bar_shows_only_once_a_command_has_run_a_while(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from mapserver.cli import _progress

    update, close = _progress.progress_bar("quick")
    update(1, 1)  # done at once: no bar (and no tqdm to load)
    close()
    assert "quick" not in capsys.readouterr().err
    monkeypatch.setattr(_progress, "SHOW_AFTER_S", 0.0)
    update, close = _progress.progress_bar("slow")
    update(10, 20)
    close()
    assert "slow" in capsys.readouterr().err


def test_process_help_names_the_decoders_default_pixel_limit(capsys: pytest.CaptureFixture[str]) -> None:
    from mapserver.cli import main
    from mapserver.ingest.decode import DEFAULT_MAX_IMAGE_PIXELS, PIXELS_ENV

    with pytest.raises(SystemExit):
        main(["process", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert str(DEFAULT_MAX_IMAGE_PIXELS) in text and f"${PIXELS_ENV}" in text

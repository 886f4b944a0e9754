"""Simulated scenarios shared by the tests of one run.

The simulator is deterministic per seed (``tests/mapserver/ingest/simulator/test_scenarios.py`` holds it to that),
so a scenario rendered twice with the same arguments gives the same files. :func:`simulate_once` renders each
(scenario, seed, format, scale, parameters, sessions) once per ``pytest`` run — whichever xdist worker asks first,
the others wait on a file lock — and copies the files into each caller's own folder, so a test may write beside
them as before. Outside a run (the bench scripts import the same helpers) it simply simulates.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from mapserver.ingest.simulator import SCENARIO_FILE, simulate

CACHE_ENV = "MAPSERVER_TEST_SIMULATIONS"  # the run's shared folder, set by tests/conftest.py


def simulate_once(
    scenario: str,
    out_dir: Path,
    *,
    seed: int = 0,
    fmt: str = "bag",
    scale: float = 1.0,
    params: Mapping[str, float] | None = None,
    only: Sequence[str] | None = None,
) -> dict[str, Any]:
    """``mapserver.ingest.simulator.simulate`` with the same arguments, rendered once per run: copy the files into
    ``out_dir`` and return the scenario.json document."""
    root = os.environ.get(CACHE_ENV)
    if not root:
        return simulate(scenario, out_dir, seed=seed, fmt=fmt, scale=scale, params=params, only=only)  # type: ignore[arg-type]
    arguments = [scenario, seed, fmt, float(scale), {k: float(v) for k, v in (params or {}).items()},
                 None if only is None else sorted(only)]  # fmt: skip
    key = hashlib.sha256(json.dumps(arguments, sort_keys=True).encode()).hexdigest()[:20]
    rendered = Path(root) / key
    with _locked(Path(root) / f"{key}.lock"):
        if not rendered.is_dir():
            partial = Path(root) / f"{key}.partial"
            shutil.rmtree(partial, ignore_errors=True)
            simulate(scenario, partial, seed=seed, fmt=fmt, scale=scale, params=params, only=only)  # type: ignore[arg-type]
            partial.rename(rendered)
    shutil.copytree(rendered, out_dir, dirs_exist_ok=True)
    return json.loads((Path(out_dir) / SCENARIO_FILE).read_text(encoding="utf-8"))


@contextmanager
def _locked(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``path`` (created) while the block runs."""
    with path.open("a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)

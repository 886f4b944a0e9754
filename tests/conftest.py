"""Run-wide test setup: one folder of simulated scenarios shared by every xdist worker (tests/simulations.py)."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest

from tests.simulations import CACHE_ENV


@pytest.fixture(scope="session", autouse=True)
def shared_simulations(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Point :func:`tests.simulations.simulate_once` at this run's folder (the workers' common temporary root)."""
    base = tmp_path_factory.getbasetemp()
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "simulations"
    root.mkdir(exist_ok=True)
    previous = os.environ.get(CACHE_ENV)
    os.environ[CACHE_ENV] = str(root)
    yield
    if previous is None:
        os.environ.pop(CACHE_ENV, None)
    else:
        os.environ[CACHE_ENV] = previous

"""Shared fixtures for engine tests: the strip world (``tests/worlds.py``)."""

from __future__ import annotations

import pytest

from tests.worlds import StripWorld


@pytest.fixture
def strip_world() -> StripWorld:
    return StripWorld()

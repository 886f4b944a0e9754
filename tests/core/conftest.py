"""Shared fixtures for engine tests: the strip world (``tests/worlds.py``)."""

from __future__ import annotations

import pytest

from core.config import Params
from tests.worlds import StripWorld


@pytest.fixture
def strip_world() -> StripWorld:
    return StripWorld()


EVERY_DEPARTURE = {"openratslam_parts": "none", "exp_settle_joint": False, "exp_loop_weight": 1.0,
                   "exp_robust_view": False}  # fmt: skip
"""Every departure of the engine from OpenRatSLAM's code on, settled on RatSLAM's fixed point, view links as precise
as odometry: the engine these tests take apart (the defaults, docs/engine.md, run three parts as OpenRatSLAM's)."""


def departing(**changes: object) -> Params:
    """Return ``Params`` with :data:`EVERY_DEPARTURE` and ``changes``."""
    return Params(**{**EVERY_DEPARTURE, **changes})  # type: ignore[arg-type]

"""Running a simulated scenario's session 2 through the online merge driver against session 1, without a database."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from core.engine import Engine
from mapserver.merge.engines import StoredMap
from mapserver.merge.online import MergeEvent, OnlineMerger, Rollback
from mapserver.processing.run import run_engine
from tests.mapserver.merge.scenario_metrics import true_alignment
from tests.simulations import simulate_once


def online_merge(
    directory: Path,
    scenario: str,
    params: Any,
    on_frame: Callable[[Any], None] | None = None,
    seed: int = 0,
    **sim: float,
) -> tuple[list[Any], list[Any], np.ndarray]:
    """Simulate ``seed``, map session 1 alone, run session 2 through the online merge driver against it.

    Returns the merge events, the rollbacks and the true alignment of session 2's map frame onto session 1's.
    ``on_frame``: called with each of session 2's frames, in order.
    """
    info = simulate_once(scenario, directory, seed=seed, params=sim, only=("session1", "session2"))
    s1, s2 = info["sessions"][:2]
    stored = Engine(params, origin=1)
    run_engine(stored, directory / s1["log"])
    stored.settle()
    merger = OnlineMerger([StoredMap(1, params, stored.snapshot())])
    current = [Engine(params, origin=2)]

    def hook(frame: Any, result: Any) -> Engine | None:
        if on_frame is not None:
            on_frame(frame)
        event = merger.observe(current[0], result, frame)
        if isinstance(event, MergeEvent | Rollback):
            current[0] = event.engine
            return event.engine
        return None

    run_engine(current[0], directory / s2["log"], on_step=hook)
    merger.finish()
    truth = true_alignment(directory, s1, s2, math.radians(params.exp_initial_em_deg))
    return merger.events, merger.rollbacks, truth

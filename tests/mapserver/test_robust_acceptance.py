"""Issue 12 part 4 acceptance: stored simulated maps with k = 1, 5, 20 injected wrong loop links.

The APE after robust relaxation stays within 1.25× of the clean map's, the health figure flags the
wrong links (most switched off; residual high with them kept, normal after), and every true loop closure
of the clean map stays on. Doing nothing (``exp_robust = false``) fails the same bound. The sweep over
more seeds and link sizes is bench/robust_relaxation.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mapserver.store.health import map_health
from tests.mapserver.robust_metrics import Simulated, inject, map_ape, simulate_single

pytestmark = pytest.mark.slow

SIZE_M = 2.0  # the wrong links join experiences 2–3 m apart


@pytest.fixture(scope="module", params=["loop", "cave3d"])
def simulated(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Simulated:
    out: Path = tmp_path_factory.mktemp(request.param)
    return simulate_single(out / request.param, request.param)


@pytest.mark.parametrize("count", [1, 5, 20])
def test_wrong_loop_links_do_not_bend_the_map(simulated: Simulated, count: int) -> None:
    stamps = simulated.state["em_stamp"]
    clean_ape = map_ape(simulated.state["em_pose"], stamps, simulated.truth)
    clean_health = map_health(simulated.params, simulated.state)
    assert clean_health["switched_off"] == 0 and clean_health["residual"] < 1.5
    robust = inject(simulated, count, SIZE_M, seed=count)
    assert robust.injected.size == count
    assert map_ape(robust.engine.map.poses, stamps, simulated.truth) <= 1.25 * clean_ape
    # the paired must-still-happen: every true loop closure of the clean map stays on
    assert robust.true_loops > 5 and robust.true_loops_on == robust.true_loops
    health = map_health(simulated.params, robust.engine.snapshot())
    assert health["switched_off"] >= max(1, int(0.8 * count))
    assert not robust.engine.map.link_active[robust.injected].all()
    assert health["residual"] < 1.2 * clean_health["residual"] and health["worst"] <= 3.0

    kept = inject(simulated, count, SIZE_M, seed=count, robust=False)
    flagged = map_health(simulated.params, kept.engine.snapshot())  # the figure with the wrong links kept
    assert flagged["worst"] > 3.0 and flagged["residual"] > 1.5 * clean_health["residual"]
    if count >= 5:  # doing nothing fails the bound
        assert map_ape(kept.engine.map.poses, stamps, simulated.truth) > 1.25 * clean_ape
    assert np.all(kept.engine.map.link_active)

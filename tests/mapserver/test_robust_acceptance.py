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

from core import LinkKind
from core import robust as robust_module
from mapserver.evaluation import interpolate_poses
from mapserver.store.health import map_health
from tests.mapserver.robust_metrics import Simulated, inject, map_ape, simulate_merged, simulate_single

pytestmark = pytest.mark.slow

SIZE_M = 2.0  # the wrong links join experiences 2–3 m apart


def _without_the_map_test(monkeypatch: pytest.MonkeyPatch) -> None:
    """Switch off the test of new links between sessions against the map as it stood
    (:func:`core.robust.contradicts_the_map`): the negative controls of the cases it also catches."""
    monkeypatch.setattr(robust_module, "contradicts_the_map", lambda start, graph, *_: np.zeros(graph[0].size, bool))


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


def test_a_mirror_fold_over_a_long_cycle_is_told_by_the_odometrys_heading_bias(tmp_path: Path) -> None:
    """``symmetric`` seed 7's single route (docs/journal.md, "the odometry's heading bias in the one-link test"): three
    mirror closures over 135 m turn 118-130° (π plus the odometry's heading bias of −0.0105 rad/m × 135 m), within the
    one-link test's drift allowance (163°), so they held a fold: APE 4.27 m, and the true closure 82 → 68 was switched
    off. Taking out the bias its two true long cycles show, they are left 160° turned and flagged: APE 1.31 m. The
    paired must-still: the true lap closure 80 → 5 stays on; every loop link whose ends lie 3 m or more apart in the
    world is off. (The other true one, 82 → 68, stays off: both its ends were reached through the false relocalisations,
    and the robot's own odometry that stands in for them misses it by 7.5 m and 42°.)"""
    sim = simulate_single(tmp_path / "symmetric", "symmetric", seed=7)
    state = sim.state
    stamps = state["em_stamp"]
    assert map_ape(state["em_pose"], stamps, sim.truth) < 2.0
    where = interpolate_poses(sim.truth, stamps, max_diff_s=0.1)[:, :2]
    loops = np.flatnonzero(np.asarray(state["em_link_kind"]) == 1)
    gap = np.linalg.norm(where[state["em_link_from"][loops]] - where[state["em_link_to"][loops]], axis=1)
    active = np.asarray(state["em_link_active"], dtype=bool)[loops]
    assert np.count_nonzero(gap >= 3.0) >= 3 and not active[gap >= 3.0].any()
    src, dst = state["em_link_from"][loops], state["em_link_to"][loops]
    assert active[(src == 80) & (dst == 5)].tolist() == [True]


def test_a_batch_of_wrong_links_is_measured_against_the_map_as_it_stood(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``loop`` map seed 3 holds two true closures (its lap closure 68 → 0 itself 1.8 m off in the world). Five
    wrong links of 2-3 m (injection seeds 1-3) join the lap's ends beside it: from all links on, the descent
    keeps two of them and switches both true closures off (APE 3.2-3.4× the clean map's), although the map as
    it stood, with the batch off, costs less (TLS 82.4 against 117.9-121.6). With the status-quo start every
    wrong link is off, both true closures stay on and the APE is the clean map's. Paired: without that start
    the failure is back."""
    sim = simulate_single(tmp_path / "loop", "loop", seed=3)
    stamps = sim.state["em_stamp"]
    clean_ape = map_ape(sim.state["em_pose"], stamps, sim.truth)

    def ratios() -> list[float]:
        return [map_ape(inject(sim, 5, SIZE_M, seed=s).engine.map.poses, stamps, sim.truth) / clean_ape
                for s in (1, 2, 3)]  # fmt: skip

    assert max(ratios()) <= 1.01
    for s in (1, 2, 3):
        robust = inject(sim, 5, SIZE_M, seed=s)
        assert robust.true_loops == 2 and robust.true_loops_on == 2
        assert not robust.engine.map.link_active[robust.injected[:5]].any()
    original = robust_module._search

    def without_status_quo(problem: object, best: object, distance: object, _status_quo: object = None) -> object:
        return original(problem, best, distance)

    monkeypatch.setattr(robust_module, "_search", without_status_quo)
    monkeypatch.setattr(robust_module, "STORED_LINK_HOLD", 0.0)  # the stored closures' prior holds them too
    assert min(ratios()) > 2.5


def test_each_start_of_the_search_gets_its_own_budget_of_solves(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The merged ``cave3d`` map (seed 0, session 2 merged into session 1) with 20 wrong links of 1-1.5 m (injection
    seed 2): polishing the first descent's answer took 254 of the check's 400 solves and the pairwise clique's the
    rest, so the status quo — the map as it stood with the batch off, TLS 358.9 against the 409.1 found — was never
    tried, three wrong links stayed on and the APE rose 4.4×. Each start has its own 400 solves: the status
    quo's start finds 350.4, every wrong link is off and the APE is the clean map's. Paired: one budget shared
    by the three starts brings the failure back once the merge links' switch prior is off too (with the prior in
    the cost, one shared budget also ends with every wrong link off). (Found on ``poseidon-lvc``'s maps: the
    intensity templates' map is where the case lives.)"""
    sim = simulate_merged(tmp_path / "cave3d", "cave3d", seed=0, preset_name="poseidon-lvc")
    stamps = sim.state["em_stamp"]
    assert sim.state["em_link_kind"].tolist().count(int(LinkKind.MERGE)) >= 1
    clean = map_ape(inject(sim, 0, 1.0, seed=0).engine.map.poses, stamps, sim.truth)
    robust = inject(sim, 20, 1.0, seed=2)
    assert robust.injected.size == 20 and not robust.engine.map.link_active[robust.injected].any()
    assert map_ape(robust.engine.map.poses, stamps, sim.truth) <= 1.01 * clean
    monkeypatch.setattr(robust_module._Problem, "fresh_budget", lambda _self: None)
    assert not inject(sim, 20, 1.0, seed=2).engine.map.link_active[robust.injected].any()  # the merge links' prior
    monkeypatch.setattr(robust_module, "MERGE_LINK_HOLD", 0.0)
    shared = inject(sim, 20, 1.0, seed=2)
    assert shared.engine.map.link_active[shared.injected].any()
    assert map_ape(shared.engine.map.poses, stamps, sim.truth) > 3.0 * clean


def test_the_map_as_it_stood_replaces_a_costlier_answer_at_any_lower_cost(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``cave3d`` map seed 4 with 20 wrong links of 1-1.5 m (injection seeds 0, 5, 6): the search's answer keeps
    some of them at a TLS cost above the status quo's (the map as it stood, the batch off) but within one
    outlier's worth, a margin the status quo would have to beat (``STATUS_QUO_MARGIN`` 1): APE up to 3.6× the
    clean map's. Taken at any lower cost, every row is the clean map's. Paired: with that margin and without the
    new-link hold (what the answer keeps fits only together, so that hold alone also keeps the map as it stood) the
    failure is back. (Found on ``poseidon-lvc``'s map.)"""
    sim = simulate_single(tmp_path / "cave3d", "cave3d", seed=4, preset_name="poseidon-lvc")
    stamps = sim.state["em_stamp"]
    clean = map_ape(sim.state["em_pose"], stamps, sim.truth)

    def worst() -> float:
        return max(map_ape(inject(sim, 20, 1.0, seed=s).engine.map.poses, stamps, sim.truth) for s in (0, 5, 6)) / clean

    assert worst() <= 1.01
    monkeypatch.setattr(robust_module, "STATUS_QUO_MARGIN", 1.0)
    assert worst() <= 1.01  # the wrong links the answer keeps fit only together: the new-link hold holds them too
    monkeypatch.setattr(robust_module, "NEW_LINK_HOLD", 0.0)
    monkeypatch.setattr(robust_module, "STORED_LINK_HOLD", 0.0)  # and the stored closures' prior
    assert worst() > 2.0


def test_wrong_links_do_not_buy_their_way_into_a_merged_map_by_switching_its_merge_links_off(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The merged ``symmetric`` map (seed 0) with 20 wrong links of 5-7.5 m (injection seed 1): the search's answer
    kept 3 of them on and switched 2 merge links and a loop closure off instead — as many links off, so TLS charged
    only the residuals, 10.0 below the map as it stood (one outlier's worth is 10.4): APE 3.2× the clean map's. Now
    the status quo holds one outlier's worth for each merge link the answer switches off (``MERGE_LINK_HOLD``): the
    clean map. Paired: without the hold and without the new-link hold (the three wrong links fit only together, so
    that hold alone also keeps the map as it stood) and without the test of new links between the sessions against
    the map as it stood (which refutes the three too) the failure is back."""
    sim = simulate_merged(tmp_path / "symmetric", "symmetric", seed=0)
    stamps = sim.state["em_stamp"]
    clean = map_ape(sim.state["em_pose"], stamps, sim.truth)
    held = inject(sim, 20, 5.0, seed=1)
    assert not held.engine.map.link_active[held.injected].any()
    assert map_ape(held.engine.map.poses, stamps, sim.truth) <= 1.01 * clean
    monkeypatch.setattr(robust_module, "MERGE_LINK_HOLD", 0.0)
    assert not inject(sim, 20, 5.0, seed=1).engine.map.link_active[held.injected].any()  # the new-link hold, too
    monkeypatch.setattr(robust_module, "NEW_LINK_HOLD", 0.0)
    monkeypatch.setattr(robust_module, "STORED_LINK_HOLD", 0.0)  # and the stored closures' prior
    assert not inject(sim, 20, 5.0, seed=1).engine.map.link_active[held.injected].any()  # and the map's test
    _without_the_map_test(monkeypatch)
    bought = inject(sim, 20, 5.0, seed=1)
    assert bought.engine.map.link_active[bought.injected].sum() == 3
    assert map_ape(bought.engine.map.poses, stamps, sim.truth) > 2.5 * clean


@pytest.fixture(scope="module")
def twin_overlap_merged(tmp_path_factory: pytest.TempPathFactory) -> Simulated:
    """The merged ``twin-overlap`` map of seed 3 (session 2 merged into session 1 online)."""
    sim = simulate_merged(tmp_path_factory.mktemp("twin-overlap") / "twin-overlap", "twin-overlap", seed=3)
    assert sim.state["em_link_kind"].tolist().count(int(LinkKind.MERGE)) >= 1
    return sim


def test_new_links_that_fit_only_together_earn_their_place_against_the_map_as_it_stood(
    twin_overlap_merged: Simulated, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The merged ``twin-overlap`` map (seed 3, session 2 merged into session 1) with 5 wrong links of 2-3 m
    (injection seed 5): two of them join neighbouring places with the same error (82 → 133, 81 → 132). Alone
    neither lowers the TLS cost of the map as it stood, so the status quo's start leaves both off (C 69.1); together
    they bend the map until each fits, and the search's answer keeps both on at C 61.7, within one outlier's worth
    (c̄² = 16): APE 1.73× the clean map's. Now each new link the answer keeps on and the status quo left off holds one
    outlier's worth for the map as it stood (``NEW_LINK_HOLD``): every wrong link off, the clean map. Paired: without
    the hold the two are back on and the failure is back."""
    sim = twin_overlap_merged
    stamps = sim.state["em_stamp"]
    clean = map_ape(sim.state["em_pose"], stamps, sim.truth)
    held = inject(sim, 5, SIZE_M, seed=5)
    assert held.injected.size == 5 and not held.engine.map.link_active[held.injected].any()
    assert held.true_loops_on == held.true_loops
    assert map_ape(held.engine.map.poses, stamps, sim.truth) <= 1.01 * clean
    monkeypatch.setattr(robust_module, "NEW_LINK_HOLD", 0.0)
    joined = inject(sim, 5, SIZE_M, seed=5)
    assert joined.engine.map.link_active[joined.injected].sum() == 2
    assert map_ape(joined.engine.map.poses, stamps, sim.truth) > 1.5 * clean


def test_a_standing_closure_traded_by_the_strain_pass_is_weighed_against_the_map_as_it_stood(
    twin_overlap_merged: Simulated, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The merged ``twin-overlap`` map (seed 3) with one wrong link of 2-3 m (injection seed 3), 82 → 138, beside the
    stored closure 139 → 86. With both on, nothing exceeds c̄ (C 46.1), so the first descent switched nothing off and
    the status quo's start was never tried; the strain pass then traded the closure for the wrong link (C 37.4, the
    closure's switch prior included): APE 1.40× the clean map's. The map as it stood, the wrong link off, costs 21.1.
    Now the status quo's start is also tried when the answer switches off a link the map stood on: the closure stays,
    the wrong link is off, the clean map. Paired: without that start the trade is back."""
    sim = twin_overlap_merged
    stamps = sim.state["em_stamp"]
    clean = map_ape(sim.state["em_pose"], stamps, sim.truth)
    original, tried = robust_module._status_quo_start, []

    def spied(problem: object, status_quo: object) -> object:
        tried.append(True)
        return original(problem, status_quo)

    monkeypatch.setattr(robust_module, "_status_quo_start", spied)
    held = inject(sim, 1, SIZE_M, seed=3)
    assert tried and held.true_loops_on == held.true_loops and not held.engine.map.link_active[held.injected].any()
    assert map_ape(held.engine.map.poses, stamps, sim.truth) <= 1.01 * clean
    monkeypatch.setattr(robust_module, "_status_quo_start", lambda _problem, _status_quo: None)
    traded = inject(sim, 1, SIZE_M, seed=3)
    assert traded.true_loops_on == traded.true_loops - 1 and traded.engine.map.link_active[traded.injected].all()
    assert map_ape(traded.engine.map.poses, stamps, sim.truth) > 1.3 * clean


def test_a_merge_link_that_stood_is_not_traded_for_a_wrong_link_by_any_start_of_the_search(
    twin_overlap_merged: Simulated, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The merged ``twin-overlap`` map (seed 3) with 20 wrong links of 5-7.5 m (injection seed 7): one of them, 2 → 104,
    joins session 1's start to session 2's approach a few experiences before the merge link 108 → 0. Switched back on
    alone in the status quo's start, it lowered the cost with the merge link switched off for it (one link off for one
    on: TLS charges both the same), so the map as it stood was itself the trade, and a merge-link hold weighed
    only between the starts' answers never saw it: APE 1.72× the clean map's. The hold is a switch prior
    in the cost itself (one outlier's worth for each merge link that was on and is off), which every start weighs: the
    merge link stays on, every wrong link is off, the clean map. Paired: without the prior the trade is back."""
    sim = twin_overlap_merged
    stamps = sim.state["em_stamp"]
    clean = map_ape(sim.state["em_pose"], stamps, sim.truth)
    merge = np.asarray(sim.state["em_link_kind"]) == int(LinkKind.MERGE)

    def settled() -> tuple[bool, float, bool]:
        injected = inject(sim, 20, 5.0, seed=7)
        active = injected.engine.map.link_active
        ape = map_ape(injected.engine.map.poses, stamps, sim.truth)
        return bool(active[: merge.size][merge].all()), ape, bool(active[injected.injected].any())

    merges_on, ape, wrong_on = settled()
    assert merges_on and not wrong_on and ape <= 1.01 * clean
    monkeypatch.setattr(robust_module, "MERGE_LINK_HOLD", 0.0)
    merges_on, ape, wrong_on = settled()
    assert not merges_on and wrong_on and ape > 1.5 * clean


def test_a_stored_loop_closure_is_not_traded_for_a_wrong_link_that_contradicts_it(
    twin_overlap_merged: Simulated, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The merged ``twin-overlap`` map (seed 3) with 5 wrong links of 5-7.5 m (injection seed 5): one of them, 90 → 138,
    contradicts the stored loop closure 139 → 86. Switched back on alone, it lowered the cost with the closure switched
    off for it (one link off for one on), in the answer and in the status quo's own start alike: APE 1.49× the clean
    map's. A loop link the finished sessions left on now carries the switch prior a merge link does
    (``STORED_LINK_HOLD``): the closure stays, every wrong link is off, the clean map. Paired: without it the trade is
    back."""
    sim = twin_overlap_merged
    stamps = sim.state["em_stamp"]
    clean = map_ape(sim.state["em_pose"], stamps, sim.truth)
    held = inject(sim, 5, 5.0, seed=5)
    assert held.true_loops_on == held.true_loops and not held.engine.map.link_active[held.injected].any()
    assert map_ape(held.engine.map.poses, stamps, sim.truth) <= 1.01 * clean
    monkeypatch.setattr(robust_module, "STORED_LINK_HOLD", 0.0)
    traded = inject(sim, 5, 5.0, seed=5)
    assert traded.true_loops_on == traded.true_loops - 1 and traded.engine.map.link_active[traded.injected].sum() == 1
    assert map_ape(traded.engine.map.poses, stamps, sim.truth) > 1.4 * clean


def test_a_wrong_link_between_sessions_that_bends_a_long_path_cheaply_is_refuted_by_the_map_as_it_stood(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The merged ``twin-overlap`` map of seed 3 as the product makes it (the merge's ties, closures facing the views)
    with 20 wrong links of 5-7.5 m (injection seed 6). 79 → 127 joins session 1 to session 2 over a path long enough
    that bending it costs less than an outlier: switched back on alone in the status quo's start, it fits at z 0.5 and
    lowers the TLS cost by 2.8 (c̄² = 16); then 77 → 115 comes on with a relocalisation's odometry link traded for it:
    APE 1.83× the clean map's (``bench/robust_merged.py --seeds 10``). Dead reckoning cannot test either (no odometry
    joins their ends) and their turns are a merge's. Now each new link between sessions is weighed against the map as
    it stood over the shortest path between its ends (:func:`core.robust.contradicts_the_map`): 77 → 115 claims one
    place where that map holds 5.8 m, z_map 1.55 > 1.5, refuted; 79 → 127 (4.6 m, within what its path allows) stays
    on without the trade, and the map is as good as the clean one (0.97×). Paired: without that test the failure is
    back."""
    sim = simulate_merged(tmp_path / "twin-overlap", "twin-overlap", seed=3, tie_hits=True, view_heading=True)
    stamps = sim.state["em_stamp"]
    clean = map_ape(sim.state["em_pose"], stamps, sim.truth)
    held = inject(sim, 20, 5.0, seed=6)
    assert held.engine.map.link_active[held.injected].sum() == 1 and held.true_loops_on == held.true_loops
    assert map_ape(held.engine.map.poses, stamps, sim.truth) <= 1.01 * clean
    _without_the_map_test(monkeypatch)
    bent = inject(sim, 20, 5.0, seed=6)
    # both wrong links on, and the reckoning link that joined the map for the odometry link traded (appended last)
    assert bent.engine.map.link_active[bent.injected].sum() == 3
    assert bent.engine.map.link_count == held.engine.map.link_count + 1
    assert map_ape(bent.engine.map.poses, stamps, sim.truth) > 1.5 * clean

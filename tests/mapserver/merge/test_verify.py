"""When a probation may end and how it is judged (mapserver.merge.verify.Probation), by hand."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from core import Action, preset
from core.se3 import compose
from mapserver.merge.hypotheses import Hypothesis, HypothesisSet
from mapserver.merge.verify import (
    OPEN_PROBATION_CAP,
    PASSED,
    PROBATION_CAP,
    REJECTED,
    WEAK_MISS_PROBATION_CAP,
    Probation,
    link_consensus,
)
from tests.mapserver.merge.online_driver import online_merge


def _probation(last_hit_m: float) -> Probation:
    rule = SimpleNamespace(probation_m=12.0, evidence_m=4.0, miss_weight=2.0, coverage_radius=1.5,
                           probation_max_m=-1.0)  # fmt: skip
    return Probation(key=1, hypothesis=None, hset=SimpleNamespace(rule=rule), shadow=None,  # type: ignore[arg-type]
                     start_m=100.0, loaded_experiences=0, last_hit_m=last_hit_m)  # fmt: skip


def test_not_before_the_probation_distance() -> None:
    assert not _probation(last_hit_m=-1.0)._may_conclude(111.9)  # 11.9 m < 12 m, no match at all
    assert _probation(last_hit_m=-1.0)._may_conclude(112.0)  # 12 m travelled, 12 m since the merge's frame


def test_not_while_the_matches_go_on() -> None:
    assert not _probation(last_hit_m=120.0)._may_conclude(123.9)  # 3.9 m after the newest match
    assert _probation(last_hit_m=120.0)._may_conclude(124.0)  # 4 m (evidence_m) after it


def test_a_probation_that_keeps_matching_ends_at_the_cap() -> None:
    """16 probation distances (``OPEN_PROBATION_CAP``), 8 once the probation has closed a loop on the stored map."""
    cap = 100.0 + OPEN_PROBATION_CAP * 12.0
    assert not _probation(last_hit_m=cap - 0.5)._may_conclude(cap - 0.1)
    assert _probation(last_hit_m=cap - 0.5)._may_conclude(cap)
    looped = 100.0 + PROBATION_CAP * 12.0
    assert looped < cap and not _probation(last_hit_m=looped - 0.5)._may_conclude(looped)
    closed = _probation(last_hit_m=looped - 0.5)
    closed.revisited = True
    assert not closed._may_conclude(looped - 0.1) and closed._may_conclude(looped)


def _at(probation: Probation, x: float, distance: float) -> None:
    probation.hypothesis.anchor_place = np.array([x, 0.0, 0.0, 0.0])  # the hit's stored place
    probation._note_revisit(distance)


def test_a_loop_is_closed_when_a_hit_comes_back_to_a_place_hit_a_probation_distance_of_driving_before() -> None:
    """By hand (probation 12 m, position tolerance 2 m): driving along stored places never closes a loop (however
    long), nor does matching one place for 29 m; coming back to a place hit 11 m of driving before does not, 12 m
    later does."""
    along = _probation(last_hit_m=-1.0)
    along.hset.rule.position_tolerance = 2.0
    along.hypothesis = SimpleNamespace(anchor_place=None)
    for d in range(0, 200):
        _at(along, x=float(d), distance=100.0 + d)
    assert not along.revisited  # 200 m of hits, each 1 m further on: a look-alike street
    back = _probation(last_hit_m=-1.0)
    back.hset.rule.position_tolerance = 2.0
    back.hypothesis = SimpleNamespace(anchor_place=None)
    _at(back, x=0.0, distance=100.0)
    _at(back, x=6.0, distance=105.0)  # away from it
    _at(back, x=1.5, distance=111.0)  # back within 2 m, but only 11 m of driving later
    assert not back.revisited
    _at(back, x=1.9, distance=112.0)  # 12 m after the first hit, 1.9 m from its place: the loop is closed
    assert back.revisited
    lingering = _probation(last_hit_m=-1.0)  # a forward view matching one place while the robot drives on
    lingering.hset.rule.position_tolerance = 2.0
    lingering.hypothesis = SimpleNamespace(anchor_place=None)
    for d in range(0, 30):
        _at(lingering, x=0.0, distance=100.0 + d)
    assert not lingering.revisited  # 29 m of hits at one place: it never left it
    _at(lingering, x=5.0, distance=130.0)
    _at(lingering, x=1.0, distance=131.0)  # away (5 m) and back: the loop is closed
    assert lingering.revisited


def test_merge_probation_max_m_sets_the_cap_in_metres_never_below_the_probation_distance() -> None:
    """A world with look-alikes longer than the cap (``twin`` turns alike 100 m) needs a longer one."""
    long = _probation(last_hit_m=299.5)
    long.hset.rule.probation_max_m = 200.0  # 200 m after the merge at 100 m, where the default cap is 192 m (16 × 12 m)
    assert not long._may_conclude(100.0 + PROBATION_CAP * 12.0) and not long._may_conclude(299.9)
    assert long._may_conclude(300.0)
    for sdr_htm in (False, True):  # the metres replace either front-end's cap
        short = _probation(last_hit_m=111.5)
        short.hset.rule.miss_weight = 0.16 if sdr_htm else 2.0
        short.hset.rule.probation_max_m = 5.0  # below the probation distance (12 m): the probation still runs it
        assert not short._may_conclude(111.9) and short._may_conclude(112.0)


def test_the_cap_does_not_close_a_probation_held_open_on_mismatches() -> None:
    """``twin`` turns alike 80 m seed 2's false merge reaches the cap 3.95 m into a run of mismatches, its matches
    stopped 14 m before: the cap does not pass it there. Held open, the run goes on to 4.49 m and rolls it back."""
    cap = 100.0 + OPEN_PROBATION_CAP * 12.0
    held = _probation(last_hit_m=cap - 14.0)
    held.miss_run_m = 3.95  # > the coverage radius (1.5 m): a run beyond the map's edge
    assert held.held_open(cap) and not held._may_conclude(cap)
    assert not held._may_conclude(cap + 30.0)  # open while the run goes on: the run or the log's end decides
    edge = _probation(last_hit_m=cap - 14.0)  # must still: a run within the map's edge ends it at the cap
    edge.miss_run_m = 1.0
    assert not edge.held_open(cap) and edge._may_conclude(cap)
    back = _probation(last_hit_m=cap + 2.0)  # and once matches come back, the probation ends as it would at the cap
    assert not back.held_open(cap + 2.0) and back._may_conclude(cap + 2.0)


def test_a_run_of_mismatches_weighs_by_the_front_ends_miss_weight() -> None:
    lvc = _probation(last_hit_m=-1.0)
    assert lvc.miss_run_limit() == 4.0  # evidence_m: LVC's misses weigh 2 hits
    sdr = _probation(last_hit_m=-1.0)
    sdr.hset.rule.miss_weight = 0.16  # the sdr-htm reader misses 60 % of true places: 12.5 × the run
    assert sdr.miss_run_limit() == 50.0
    heavier = _probation(last_hit_m=-1.0)
    heavier.hset.rule.miss_weight = 4.0  # never shorter than evidence_m
    assert heavier.miss_run_limit() == 4.0


def test_the_cusum_of_a_weak_miss_front_end_by_hand() -> None:
    sdr = _probation(last_hit_m=-1.0)
    sdr.hset.rule.miss_weight = 0.25  # a hit metre cancels 4 miss metres
    for hit, miss in ((0.0, 3.0), (0.0, 2.0), (0.5, 0.0), (0.0, 1.0), (1.0, 0.0), (0.0, 0.5)):
        sdr._cusum(hit, miss)
    # 3, 5, 5 − 2 = 3, 4, max(0, 4 − 4) = 0, 0.5
    assert sdr.cusum_m == 0.5
    lvc = _probation(last_hit_m=-1.0)  # LVC's misses weigh 2: its run rule decides, no CUSUM
    lvc._cusum(0.0, 10.0)
    assert lvc.cusum_m == 0.0


def test_a_probation_the_log_cut_short_is_judged_on_what_it_saw() -> None:
    against = _probation(last_hit_m=110.0)
    against.hypothesis = SimpleNamespace(post_hit_m=3.0, post_miss_m=1.6)  # net 3 − 2 · 1.6 = −0.2 m
    assert against.conclude_at_end(120.0) == REJECTED and "net -0.20 m" in against.reason
    settled = _probation(last_hit_m=110.0)
    settled.hypothesis = SimpleNamespace(post_hit_m=3.0, post_miss_m=1.4)  # net +0.2 m, matches stopped 10 m back
    assert settled.conclude_at_end(120.0) == PASSED and "net 0.20 m" in settled.reason
    assert settled._conclude() == REJECTED  # a probation run to its end would have asked for half evidence_m
    matching = _probation(last_hit_m=117.0)  # the newest match 3 m back: kept (a look-alike could not be told)
    matching.hypothesis = SimpleNamespace(post_hit_m=15.0, post_miss_m=0.0)
    assert matching.conclude_at_end(120.0) == PASSED and "newest match 3.00 m before its end" in matching.reason


def test_an_lvc_probation_passes_only_on_the_evidence_distance_of_matches() -> None:
    """``twin`` turns alike 60 m seed 1's false merge ends its probation on 2.91 m of matches and no mismatch
    (net +2.91 m, over the half line of 2 m), which is not enough: an LVC probation must also have matched over
    ``evidence_m`` (4 m here). Must still: 4 m of matches pass; a front-end with weak misses (``sdr-htm``) keeps the
    half line."""
    scarce = _probation(last_hit_m=103.0)
    scarce.hypothesis = SimpleNamespace(post_hit_m=2.91, post_miss_m=0.0)
    assert scarce._conclude() == REJECTED and "net 2.91 m" in scarce.reason
    enough = _probation(last_hit_m=103.0)
    enough.hypothesis = SimpleNamespace(post_hit_m=4.0, post_miss_m=0.0)
    assert enough._conclude() == PASSED
    sdr = _probation(last_hit_m=103.0)
    sdr.hset.rule.miss_weight = 0.16
    sdr.hypothesis = SimpleNamespace(post_hit_m=2.91, post_miss_m=0.0)
    assert sdr._conclude() == PASSED


def test_a_probation_held_open_on_mismatches_when_the_log_ends_is_judged_as_one_that_ran_its_distance() -> None:
    held = _probation(last_hit_m=110.3)  # matches stopped 54 m before the end, then 3.9 m of mismatches in a row
    held.miss_run_m = 3.9  # > the coverage radius (1.5 m): held open
    held.hypothesis = SimpleNamespace(post_hit_m=9.85, post_miss_m=4.335)  # net 9.85 − 2 · 4.335 = 1.18 m
    assert held.held_open(164.3)
    assert held.conclude_at_end(164.3) == REJECTED and "needed 2.00 m" in held.reason  # half of evidence_m
    confirmed = _probation(last_hit_m=110.3)  # must still: the same hold with the merge confirmed first
    confirmed.miss_run_m = 3.9
    confirmed.hypothesis = SimpleNamespace(post_hit_m=12.0, post_miss_m=4.0)  # net 4 m
    assert confirmed.conclude_at_end(164.3) == PASSED
    short = _probation(last_hit_m=110.3)  # a run of mismatches before the probation distance: cut short, lenient
    short.miss_run_m = 3.9
    short.hypothesis = SimpleNamespace(post_hit_m=9.85, post_miss_m=4.335)
    assert not short.held_open(111.0) and short.conclude_at_end(111.0) == PASSED


def test_a_weak_miss_front_end_keeps_the_shorter_cap() -> None:
    sdr = _probation(last_hit_m=100.0 + WEAK_MISS_PROBATION_CAP * 12.0 - 0.5)
    sdr.hset.rule.miss_weight = 0.16  # sdr-htm: its probation's length is the cap
    assert not sdr._may_conclude(100.0 + WEAK_MISS_PROBATION_CAP * 12.0 - 0.1)
    assert sdr._may_conclude(100.0 + WEAK_MISS_PROBATION_CAP * 12.0)
    assert WEAK_MISS_PROBATION_CAP < PROBATION_CAP
    lvc = _probation(last_hit_m=100.0 + WEAK_MISS_PROBATION_CAP * 12.0 - 0.5)  # LVC runs on while it matches
    assert not lvc._may_conclude(100.0 + WEAK_MISS_PROBATION_CAP * 12.0)


def test_a_probation_does_not_close_on_a_run_of_mismatches_longer_than_the_maps_edge_explains() -> None:
    leaving = _probation(last_hit_m=120.0)
    leaving.miss_run_m = 1.5  # within the coverage radius of the last stored places: leaving the map's edge
    assert leaving._may_conclude(124.0)
    contradicted = _probation(last_hit_m=120.0)
    contradicted.miss_run_m = 2.1  # more than that: wait for more evidence
    assert not contradicted._may_conclude(124.0) and not contradicted._may_conclude(150.0)
    assert not contradicted._may_conclude(100.0 + PROBATION_CAP * 12.0)  # nor the cap (test below)
    sdr = _probation(last_hit_m=120.0)
    sdr.hset.rule.miss_weight = 0.16  # weak misses: runs of mismatches on true ground are common
    sdr.miss_run_m = 5.0
    assert sdr._may_conclude(124.0)


def test_link_consensus_counts_the_links_that_agree_on_one_alignment_by_hand() -> None:
    turned = np.array([10.0, 0.0, 0.0, math.pi / 2])  # the session's odometry, turned 90° and moved 10 m east
    odometry = [np.array([0.0, 0.0, 0.0, 0.0]), np.array([5.0, 0.0, 0.0, 0.0]), np.array([0.0, 5.0, 0.0, 0.3])]
    stored = [np.array([10.0, 0.0, 0.0, math.pi / 2]), np.array([10.0, 5.0, 0.0, math.pi / 2]),
              np.array([5.0, 0.0, 0.0, math.pi / 2 + 0.3])]  # fmt: skip  # turned ⊕ o, by hand
    assert np.allclose(compose(turned, np.stack(odometry)), np.stack(stored))
    links = list(zip(stored, odometry, strict=True))
    assert link_consensus(links, tolerance=0.5) == 3
    links.append((np.array([50.0, 50.0, 0.0, 0.0]), np.array([1.0, 1.0, 0.0, 0.0])))  # another alignment
    assert link_consensus(links, tolerance=0.5) == 3
    scattered = [(np.array([4.0, 0.0, 0.0, 0.0]), np.zeros(4)), (np.array([0.0, 4.0, 0.0, 0.0]), np.zeros(4)),
                 (np.array([-4.0, 2.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0, 0.0]))]  # fmt: skip
    assert link_consensus(scattered, tolerance=2.0) == 1  # each puts the others' robot 5.4-9.2 m off their place
    assert link_consensus([], tolerance=2.0) == 0


def _linked_probation(stored: np.ndarray, loose: bool = False) -> Probation:
    """A probation whose merge put the session's odometry onto the stored map unchanged (identity alignment)."""
    rule = SimpleNamespace(probation_m=12.0, evidence_m=4.0, miss_weight=2.0, coverage_radius=1.5, reject_m=2.0,
                           position_tolerance=1.0, probation_max_m=-1.0)  # fmt: skip
    hset = SimpleNamespace(rule=rule, places=SimpleNamespace(poses=stored, loose=loose))
    hypothesis = SimpleNamespace(post_hit_m=6.0, post_miss_m=0.0, predict=lambda odometry: np.asarray(odometry))
    return Probation(key=1, hypothesis=hypothesis, hset=hset, shadow=None,  # type: ignore[arg-type]
                     start_m=100.0, loaded_experiences=len(stored))  # fmt: skip


def _close_loops(probation: Probation, closures: list[tuple[int, tuple[float, float]]]) -> None:
    """Loop closures onto stored experience ``e`` seen with the session's odometry at (x, y)."""
    for experience, (x, y) in closures:
        track = SimpleNamespace(last=(0, np.array([x, y, 0.0, 0.0])), distance=110.0)
        probation._check_link(track, SimpleNamespace(action=Action.CREATE_EDGE, experience=experience))  # type: ignore[arg-type]


def test_loop_links_that_disagree_reject_a_merge_only_when_they_agree_on_another_alignment() -> None:
    """``cave3d`` with ``sdr-htm`` (seed 6): a true merge met 3 false front-end closures 2–4 m off, each its own
    way, beside 2 that agreed; counting every disagreeing link rolled it back. Must not: scattered disagreeing
    links reject nothing; must still: two that put the robot 20 m east both reject it, outnumbering one agreeing."""
    stored = np.array([[0.0, 0.0, 0.0, 0.0], [10.0, 0.0, 0.0, 0.0], [24.0, 0.0, 0.0, 0.0], [10.0, 4.0, 0.0, 0.0],
                       [2.0, -3.0, 0.0, 0.0], [20.0, 0.0, 0.0, 0.0], [30.0, 0.0, 0.0, 0.0]])  # fmt: skip
    scattered = _linked_probation(stored)
    _close_loops(scattered, [(0, (0.0, 0.0)), (1, (10.0, 0.0)), (2, (20.0, 0.0)), (3, (10.0, 0.0)), (4, (5.0, 0.0))])
    assert (scattered.links_agree, scattered.links_disagree, scattered.links_consensus) == (2, 3, 1)
    assert scattered._contradiction() == ""
    elsewhere = _linked_probation(stored)
    _close_loops(elsewhere, [(0, (0.0, 0.0)), (5, (0.0, 0.0)), (6, (10.0, 0.0))])  # both: the robot 20 m east
    assert (elsewhere.links_agree, elsewhere.links_disagree, elsewhere.links_consensus) == (1, 2, 2)
    assert elsewhere._contradiction().startswith("2 loop links agree on another alignment")
    outvoted = _linked_probation(stored)  # the same two against two agreeing: not more than them
    _close_loops(outvoted, [(0, (0.0, 0.0)), (1, (10.0, 0.0)), (5, (0.0, 0.0)), (6, (10.0, 0.0))])
    assert outvoted.links_consensus == 2 and outvoted._contradiction() == ""


def test_an_agreeing_loop_link_places_the_prediction_on_its_experience_and_counts_as_a_match() -> None:
    """:meth:`Probation._follow_link`: a closure onto a stored experience within twice the position tolerance of the
    prediction moves the alignment so that it predicts the robot on that experience, at the prediction's own
    heading, and restarts the matches' clock; one farther off (a disagreeing link) moves nothing, nor does an
    agreeing one of a front-end that places its views loosely."""
    stored = np.array([[1.2, 0.5, 0.0, 2.0], [9.0, 0.0, 0.0, 0.0]])
    probation = _linked_probation(stored)
    probation.hypothesis = Hypothesis(alignment=np.array([0.0, 0.0, 0.0, 0.1]), born=0)
    odometry = np.array([1.0, 0.0, 0.0, 0.3])
    before = probation.hypothesis.predict(odometry)  # (cos 0.1, sin 0.1, 0, 0.4): 0.53 m from experience 0
    probation._check_link(SimpleNamespace(last=(0, odometry), distance=107.0),  # type: ignore[arg-type]
                          SimpleNamespace(action=Action.CREATE_EDGE, experience=0))  # type: ignore[arg-type]
    assert probation.links_agree == 1 and probation.last_hit_m == 107.0
    assert probation.since_match_m(109.5) == pytest.approx(2.5)
    np.testing.assert_allclose(probation.hypothesis.predict(odometry), [1.2, 0.5, 0.0, before[3]], atol=1e-12)
    assert before[3] == pytest.approx(0.4)
    moved = probation.hypothesis.alignment.copy()
    probation._check_link(SimpleNamespace(last=(0, odometry), distance=108.0),  # type: ignore[arg-type]
                          SimpleNamespace(action=Action.CREATE_EDGE, experience=1))  # type: ignore[arg-type]
    assert probation.links_disagree == 1 and probation.last_hit_m == 107.0
    np.testing.assert_array_equal(probation.hypothesis.alignment, moved)
    loose = _linked_probation(stored, loose=True)  # sdr-htm: its own closures are not followed
    loose.hypothesis = Hypothesis(alignment=np.array([0.0, 0.0, 0.0, 0.1]), born=0)
    loose._check_link(SimpleNamespace(last=(0, odometry), distance=107.0),  # type: ignore[arg-type]
                      SimpleNamespace(action=Action.CREATE_EDGE, experience=0))  # type: ignore[arg-type]
    assert loose.links_agree == 1 and loose.last_hit_m == -1.0
    np.testing.assert_array_equal(loose.hypothesis.alignment, [0.0, 0.0, 0.0, 0.1])


def test_a_true_merge_stands_when_the_robot_drives_on_past_the_stored_maps_end(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``twin-overlap`` with a 40 m look-alike holding turns, seed 2 (``circle``; docs/journal.md, "an LVC
    probation slides its prediction along a place instead of pinning it there"): session 2 merges at its true place
    (frame 70) and drives 83 m on session 1's ground, then past the end of session 1's map, whose last views it keeps
    matching for metres. Re-anchoring the probation's prediction on every hit held it on those
    last places while the robot drove 8 m on (a run of 4.07 m of mismatches after 83.5 m of matches: rolled back);
    dead-reckoned on from the first hit at a place, the prediction leaves the map with the robot and the merge
    passes. Must still (the other half of the pair): with every hit re-anchoring, the run rule rolls it back."""
    circle = preset("circle")
    events, rollbacks, truth = online_merge(tmp_path / "once", "twin-overlap", circle, seed=2, lookalike_m=40.0,
                                            lookalike_turns=1.0)  # fmt: skip
    assert rollbacks == [] and len(events) == 1
    assert events[0].evidence["verification"]["status"] == "passed"
    t = events[0].record.transform
    assert math.hypot(t[0] - truth[0], t[1] - truth[1]) < 5.0  # the true alignment (3.5 m off at the map origin)
    pinning = HypothesisSet.reanchor
    monkeypatch.setattr(HypothesisSet, "reanchor", staticmethod(lambda h, seen, odo, once=True: pinning(h, seen, odo,
                                                                                                          False)))
    events, rollbacks, _ = online_merge(tmp_path / "every", "twin-overlap", circle, seed=2, lookalike_m=40.0,
                                        lookalike_turns=1.0)  # fmt: skip
    assert events == [] and len(rollbacks) == 1
    assert "mismatches in a row" in rollbacks[0].event.evidence["verification"]["reason"]

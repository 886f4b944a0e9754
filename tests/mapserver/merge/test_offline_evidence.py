"""The offline merge's evidence: miss runs along a map's chain and the probation an online merge would have run."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapserver.merge.hypotheses import HIT, MISS, UNMAPPED, EvidenceRule
from mapserver.merge.offline_evidence import (
    ChainEnd,
    OfflineEvidence,
    _chain_ends,
    _longest_miss_run,
    _loop_closed_at,
    _probation_window,
)
from mapserver.merge.verify import Probation

H, M, U = HIT, MISS, UNMAPPED


def _street(n: int) -> np.ndarray:
    """Places in B of n trials 1 m apart along a straight street (x = 1, 2, …, n m): no loop."""
    return np.column_stack([np.arange(1.0, n + 1.0), np.zeros((n, 3))])


def _evidence(
    probation_run: float, reverse: OfflineEvidence | None = None, ends: tuple[ChainEnd, ...] = ()
) -> OfflineEvidence:
    return OfflineEvidence(hit_m=30.0, miss_m=2.0, unmapped_m=0.0, turn_rad=3.0, evidence_m=4.0, miss_weight=2.0,
                           hits=30, misses=2, probation=(20.0, probation_run, 20.0), reverse=reverse,
                           ends=ends)  # fmt: skip


def _end(miss_m: float, own_x: float, seen_x: float = 0.0) -> ChainEnd:
    return ChainEnd(miss_m, (own_x, 0.0, 0.0), (seen_x, 0.0, 0.0))


def test_a_miss_run_is_the_miss_metres_between_two_hits_unmapped_trials_neither_adding_nor_breaking() -> None:
    steps = np.array([0.0, 1.0, 1.0, 1.0, 0.5, 2.0, 1.0, 1.0])
    outcomes = np.array([H, M, M, H, M, U, M, H])
    # runs: trials 1–2 (2 m), trials 4–6 (0.5 m + 1 m; the 2 m unmapped between them add nothing)
    assert _longest_miss_run(steps, outcomes == H, outcomes == M) == 2.0
    assert _longest_miss_run(steps, outcomes == H, np.zeros(8, dtype=bool)) == 0.0


def test_the_probation_lasts_its_distance_then_ends_evidence_metres_after_the_newest_hit() -> None:
    rule = EvidenceRule.for_map(1.0, 3.0, 0.5, 4.0, 6.0)  # coverage radius max(1, 3 / 2) = 1.5 m
    steps = np.ones(13)  # trials 1 m apart after the anchor, at 1, 2, …, 13 m
    outcomes = np.array([H, H, M, M, M, H, M, U, U, U, U, U, U])
    # hits at 1, 2 and 6 m; past 6 m (probation_m) it ends 4 m (evidence_m) after the newest hit: at 10 m, the
    # 1 m of misses since that hit being what leaving the map's edge explains (within the coverage radius)
    metres, run, score = _probation_window(steps, outcomes, _street(13), 6.0, rule)
    assert (metres, run) == (10.0, 3.0)  # misses 3–5 m (3 m) and 7 m (1 m): the window's longest run
    assert score == pytest.approx(3.0 - 2.0 * 4.0)
    metres, run, _ = _probation_window(np.ones(120), np.full(120, H), _street(120), 6.0, rule)
    assert (metres, run) == (96.0, 0.0)  # matches that never stop, no loop: OPEN_PROBATION_CAP (16) distances
    longer = EvidenceRule.for_map(1.0, 3.0, 0.5, 4.0, 6.0, probation_max_m=55.0)  # merge_probation_max_m
    assert _probation_window(np.ones(120), np.full(120, H), _street(120), 6.0, longer)[0] == 55.0
    shorter = EvidenceRule.for_map(1.0, 3.0, 0.5, 4.0, 6.0, probation_max_m=2.0)  # never below probation_m
    assert _probation_window(np.ones(120), np.full(120, H), _street(120), 6.0, shorter)[0] == 6.0


def _there_and_back(n: int) -> np.ndarray:
    """Places in B of n trials 1 m apart: out along x from 0 to 10 m (trials at 1–11 m), then back, and so on."""
    x = 10.0 - np.abs((np.arange(n) % 20) - 10.0)
    return np.column_stack([x, np.zeros((n, 3))])


def test_a_chain_closes_a_loop_on_the_other_map_when_its_hits_leave_a_place_and_come_back() -> None:
    travelled, hits = np.arange(1.0, 41.0), np.ones(40, dtype=bool)
    # by hand, tolerance 3 m, probation 6 m: back at 15 m the hit is at x = 6; the newest hit within 3 m of it at
    # least 6 m of driving before is the one at 9 m (x = 8), and the hit at 11 m (x = 10) lies 4 m away; at 14 m
    # (x = 7) the newest is at 8 m (x = 7) and every hit in between (x = 7 … 10) lies within 3 m: not yet
    assert _loop_closed_at(travelled, hits, _there_and_back(40), 6.0, 3.0) == 15.0
    assert _loop_closed_at(travelled, hits, _street(40), 6.0, 3.0) == np.inf  # never back: no loop
    lingering = np.zeros((40, 4))  # 40 m of hits at one place: the chain never left it
    assert _loop_closed_at(travelled, hits, lingering, 6.0, 3.0) == np.inf
    only_out = hits.copy()
    only_out[11:] = False  # the hits stop at the far end: nothing comes back
    assert _loop_closed_at(travelled, only_out, _there_and_back(40), 6.0, 3.0) == np.inf


def test_a_window_that_closed_a_loop_on_the_other_map_keeps_the_shorter_cap() -> None:
    rule = EvidenceRule.for_map(1.0, 3.0, 0.5, 4.0, 6.0)
    everywhere = np.full(120, H)
    assert _probation_window(np.ones(120), everywhere, _there_and_back(120), 6.0, rule)[0] == 48.0  # PROBATION_CAP
    assert _probation_window(np.ones(120), everywhere, _street(120), 6.0, rule)[0] == 96.0
    # out 60 m and back: at 65 m (x = 56) the newest hit within 3 m at least 6 m before is at 59 m (x = 59), and
    # the turn at 60 m (x = 60) lies 4 m away: the loop closes at 65 m, past 48 m, and the window ends there
    late = np.vstack([_street(60), _street(60)[::-1]])
    assert _probation_window(np.ones(120), everywhere, late, 6.0, rule)[0] == 65.0


def test_a_probation_whose_matches_stopped_on_a_run_of_misses_is_held_open_until_a_hit_or_the_chains_end() -> None:
    rule = EvidenceRule.for_map(1.0, 3.0, 0.5, 4.0, 6.0)
    to_the_end = np.array([H, H, M, M, M, H, M, M, M, M, M, U, U])
    # at 10 m its matches stopped 4 m back on 4 m of misses (> 1.5 m): held open to the chain's end, the run whole
    assert _probation_window(np.ones(13), to_the_end, _street(13), 6.0, rule)[:2] == (13.0, 5.0)
    back = np.array([H, H, M, M, M, H, M, M, M, U, H] + [U] * 9)
    # held from 10 m on 3 m of misses; the hit at 11 m brings the matches back: it ends 4 m after it, at 15 m
    metres, run, score = _probation_window(np.ones(20), back, _street(20), 6.0, rule)
    assert (metres, run) == (15.0, 3.0)
    assert score == pytest.approx(4.0 - 2.0 * 6.0)
    # past the cap too: matches until 40 m, 2 m of misses, held from 44 m; the cap (48 m) does not close it
    capped = np.array([H] * 40 + [M] * 2 + [U] * 8 + [M] * 2 + [U] * 2)
    assert _probation_window(np.ones(54), capped, _street(54), 6.0, rule)[:2] == (54.0, 4.0)
    weak = EvidenceRule.for_map(1.0, 3.0, 0.5, 4.0, 6.0, miss_weight=0.16)
    # a front-end with weak misses is never held open (as online): it ends at 10 m as the run rule alone says
    assert _probation_window(np.ones(13), to_the_end, _street(13), 6.0, weak)[:2] == (10.0, 4.0)


def test_an_alignment_stands_only_where_neither_maps_probation_meets_a_run_of_evidence_metres() -> None:
    assert _evidence(3.9).passed  # must still: runs shorter than evidence_m
    assert not _evidence(4.0).passed and "failing views in a row" in _evidence(4.0).reason()
    assert _evidence(1.0, reverse=_evidence(3.9)).passed
    refused = _evidence(1.0, reverse=_evidence(4.5))
    assert not refused.passed and "the other map's chain meets 4.5 m" in refused.reason()


def test_a_chains_ends_are_the_failing_metres_in_a_row_right_before_its_first_hit_and_after_its_last() -> None:
    steps = np.array([0.0, 1.0, 0.5, 1.0, 1.0, 1.0, 2.0, 3.0, 0.7, 1.0])
    outcomes = np.array([U, M, M, H, M, H, M, M, U, M])
    pose = np.arange(30, dtype=np.float64).reshape(10, 3)
    seen = -pose
    first, last = _chain_ends(steps, outcomes, pose, seen)
    assert first == ChainEnd(1.5, (9.0, 10.0, 11.0), (-9.0, -10.0, -11.0))  # trials 1-2 right before hit 3
    # trials 6-7 right after hit 5; trial 9's miss lies past unmapped ground (trial 8): the chain had parted there
    assert last == ChainEnd(5.0, (15.0, 16.0, 17.0), (-15.0, -16.0, -17.0))
    assert _chain_ends(steps, np.array([M, H, H, U, M, M, M, M, M, H]), pose, seen)[1].miss_m == 0.0  # ends on a hit
    assert _chain_ends(steps, np.full(10, M), pose, seen) == ()  # no hit, no end of agreement


def test_two_maps_that_both_drive_on_past_the_far_end_of_their_agreement_and_both_disagree_are_not_merged() -> None:
    """``twin`` 10 m alike with turns, seed 6 offline: past the stretch's far end A met 2.1 m of failing views and
    B 3.2 m, every other rule passed. Paired: one map's misses past an end alone (a session driving on past the other
    map's end, a dead-reckoned second lap: ``symmetric-overlap`` seed 7, 8.6 m), two-sided ones under
    ``evidence_m`` and two-sided ones at the near ends (walked backwards from the anchor) still merge."""
    # A's agreement runs from B's place at x = 10 to x = 30; B drove it the same way (own ends at 10 and 30)
    b_same = _evidence(0.0, ends=(_end(0.0, 10.0), _end(3.2, 30.0)))
    parted = _evidence(2.1, reverse=b_same, ends=(_end(0.9, 0.0, 10.0), _end(2.1, 50.0, 30.0)))
    assert parted.parting_m == pytest.approx(5.3)  # the far ends: 2.1 + 3.2 (the near end is one-sided anyway)
    assert not parted.passed and "both maps drive on over each other's ground" in parted.reason()
    # must still: one-sided misses however long, two-sided ones under evidence_m, and two-sided near ends
    one_sided = _evidence(0.0, reverse=_evidence(0.0, ends=(_end(0.0, 10.0), _end(0.0, 30.0))),
                          ends=(_end(0.0, 0.0, 10.0), _end(8.6, 50.0, 30.0)))  # fmt: skip
    assert one_sided.parting_m == 0.0 and one_sided.passed
    short = _evidence(2.1, reverse=_evidence(0.0, ends=(_end(0.0, 10.0), _end(1.8, 30.0))),
                      ends=(_end(0.9, 0.0, 10.0), _end(2.1, 50.0, 30.0)))  # fmt: skip
    assert short.parting_m == pytest.approx(3.9) and short.passed
    near = _evidence(0.0, reverse=_evidence(0.0, ends=(_end(2.0, 10.0), _end(0.0, 30.0))),
                     ends=(_end(2.9, 0.0, 10.0), _end(0.0, 50.0, 30.0)))  # fmt: skip
    assert near.parting_m == 0.0 and near.passed
    # B drove the stretch the other way: its last hit lies at A's near end, so the far ends are not the same end
    b_back = _evidence(0.0, ends=(_end(0.0, 30.0), _end(3.2, 10.0)))
    assert _evidence(0.0, reverse=b_back, ends=(_end(0.0, 0.0, 10.0), _end(2.1, 50.0, 30.0))).parting_m == 0.0
    assert _evidence(0.0, ends=(_end(5.0, 0.0, 10.0), _end(5.0, 50.0, 30.0))).parting_m == 0.0  # no reverse walk


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.tuples(st.integers(0, 6), st.integers(0, 2), st.booleans(), st.floats(0.0, 3.0)), max_size=40),
    st.floats(0.5, 12.0),
)
def test_the_offline_loop_test_closes_where_the_online_probation_first_says_revisited(
    trials: list[tuple[int, int, bool, float]], probation_m: float
) -> None:
    """Differential: :func:`_loop_closed_at` (all hits at once) against the online rule replayed hit by hit
    (:meth:`mapserver.merge.verify.Probation._note_revisit` on a stand-in probation), on random chains of hits and
    misses, steps, and places on a 3 m grid (two places are the same, neighbours at exactly the 3 m tolerance, or
    farther: every case of near and far); the first hit the online rule calls a loop is where the offline window's
    cap changes."""
    tolerance = 3.0
    steps = np.array([t[3] for t in trials])
    travelled = np.cumsum(steps)
    hit = np.array([t[2] for t in trials], dtype=bool)
    seen = np.array([[3.0 * t[0], 3.0 * t[1], 0.0, 0.0] for t in trials]).reshape(-1, 4)
    online = SimpleNamespace(
        hypothesis=SimpleNamespace(anchor_place=None), revisited=False, hit_places=[],
        hset=SimpleNamespace(rule=SimpleNamespace(position_tolerance=tolerance, probation_m=probation_m)),
    )  # fmt: skip
    first = np.inf
    for row in np.flatnonzero(hit).tolist():
        online.hypothesis.anchor_place = seen[row]
        Probation._note_revisit(online, float(travelled[row]))  # type: ignore[arg-type]
        if online.revisited:
            first = float(travelled[row])
            break
    assert _loop_closed_at(travelled, hit, seen, probation_m, tolerance) == first

"""When a probation may end and how it is judged (mapserver.merge.verify.Probation), by hand."""

from __future__ import annotations

from types import SimpleNamespace

from mapserver.merge.verify import PASSED, PROBATION_CAP, REJECTED, WEAK_MISS_PROBATION_CAP, Probation


def _probation(last_hit_m: float) -> Probation:
    rule = SimpleNamespace(probation_m=12.0, evidence_m=4.0, miss_weight=2.0, coverage_radius=1.5)
    return Probation(key=1, hypothesis=None, hset=SimpleNamespace(rule=rule), shadow=None,  # type: ignore[arg-type]
                     start_m=100.0, loaded_experiences=0, last_hit_m=last_hit_m)  # fmt: skip


def test_not_before_the_probation_distance() -> None:
    assert not _probation(last_hit_m=-1.0)._may_conclude(111.9)  # 11.9 m < 12 m, no match at all
    assert _probation(last_hit_m=-1.0)._may_conclude(112.0)  # 12 m travelled, 12 m since the merge's frame


def test_not_while_the_matches_go_on() -> None:
    assert not _probation(last_hit_m=120.0)._may_conclude(123.9)  # 3.9 m after the newest match
    assert _probation(last_hit_m=120.0)._may_conclude(124.0)  # 4 m (evidence_m) after it


def test_a_probation_that_keeps_matching_ends_at_the_cap() -> None:
    cap = 100.0 + PROBATION_CAP * 12.0
    assert not _probation(last_hit_m=cap - 0.5)._may_conclude(cap - 0.1)
    assert _probation(last_hit_m=cap - 0.5)._may_conclude(cap)


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
    assert contradicted._may_conclude(100.0 + PROBATION_CAP * 12.0)  # the cap still ends it
    sdr = _probation(last_hit_m=120.0)
    sdr.hset.rule.miss_weight = 0.16  # weak misses: runs of mismatches on true ground are common
    sdr.miss_run_m = 5.0
    assert sdr._may_conclude(124.0)

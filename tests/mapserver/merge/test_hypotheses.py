"""The merge decision's pieces on hand-built maps: place predictions, scores, the decision rule, resume arrays."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.localview import LocalViewCells
from core.se3 import compose
from mapserver.merge.confirm import Observation
from mapserver.merge.hypotheses import (
    HELD,
    HIT,
    MAX_HITS,
    MISS,
    PLACE_EXTENT,
    UNMAPPED,
    EvidenceRule,
    Hypothesis,
    HypothesisSet,
    StoredPlaces,
    Track,
    decide,
)
from mapserver.merge.resume import MergerState
from tests.mapserver.merge.sessions import PARAMS

RULE = EvidenceRule.for_map(spacing=1.0, position_tolerance=1.5, yaw_tolerance=0.5, evidence_m=-1.0, probation_m=-1.0)
RNG = np.random.default_rng(7)
TEMPLATES = RNG.uniform(0.0, 1.0, size=(6, PARAMS.template_y_size, PARAMS.template_x_size)).astype(np.float32)
OTHER = RNG.uniform(0.0, 1.0, size=(PARAMS.template_y_size, PARAMS.template_x_size)).astype(np.float32)


def _places(panoramic: bool = False) -> StoredPlaces:
    """Six stored experiences 1 m apart along x, heading east, each with its own template (0..5)."""
    cells = LocalViewCells(PARAMS)
    cells.add_templates(TEMPLATES, TEMPLATES.reshape(6, -1).mean(axis=1, dtype=np.float64))
    poses = np.array([[float(i), 0.0, 0.0, 0.0] for i in range(6)])
    return StoredPlaces(cells, poses, np.arange(6), PARAMS.vt_match_threshold, panoramic, RULE)


def _view(i: int) -> tuple[np.ndarray, float]:
    view = TEMPLATES[i] if i >= 0 else OTHER
    return view, float(view.mean(dtype=np.float64))


def test_the_rule_at_the_map_scale() -> None:
    assert (RULE.evidence_m, RULE.probation_m, RULE.reject_m) == (4.0, 12.0, 2.0)  # 4, 12 spacings; max(2, 1.5)
    assert RULE.coverage_radius == 1.0 and RULE.history_m == 12.0
    off = EvidenceRule.for_map(1.0, 1.5, 0.5, evidence_m=0.0, probation_m=0.0)
    assert (off.evidence_m, off.probation_m) == (0.0, 0.0)


def test_a_place_predicts_its_templates_and_nothing_elsewhere() -> None:
    places = _places()
    outcome, seen = places.test(np.array([2.2, 0.1, 0.0, 0.1]), *_view(2))
    assert outcome == HIT
    np.testing.assert_allclose(seen, [2.0, 0.0, 0.0, 0.0])  # the matched experience (forward view: no offset)
    assert places.test(np.array([2.2, 0.1, 0.0, 0.1]), *_view(-1))[0] == MISS  # mapped, the view is not there
    assert places.test(np.array([3.0, 0.0, 0.0, 0.0]), *_view(1))[0] == MISS  # its place is 2 m off (> 1.5 m)
    assert places.test(np.array([2.0, 5.0, 0.0, 0.0]), *_view(2))[0] == UNMAPPED  # nobody was there
    assert places.test(np.array([2.0, 0.0, 0.0, math.pi]), *_view(2))[0] == UNMAPPED  # facing the other way
    assert _places(panoramic=True).test(np.array([2.0, 0.0, 0.0, math.pi]), *_view(2))[0] == HIT


def test_a_forward_views_heading_does_not_turn_the_place_a_hit_re_anchors_on() -> None:
    """``vt_shift_heading``: template 2 turned by one column matches it with a heading of about one column
    (``camera_fov_deg``/32), which a merge's anchor takes; the place a hit re-anchors a hypothesis on keeps the
    stored experience's heading (forward views' per-hit headings jitter), while a panoramic offset turns it."""
    cells = LocalViewCells(PARAMS.replace(vt_shift_heading=True))
    cells.add_templates(TEMPLATES, TEMPLATES.reshape(6, -1).mean(axis=1, dtype=np.float64))
    poses = np.array([[float(i), 0.0, 0.0, 0.0] for i in range(6)])
    places = StoredPlaces(cells, poses, np.arange(6), PARAMS.vt_match_threshold, False, RULE)
    view = np.roll(TEMPLATES[2], 1, axis=1)
    mean = float(view.mean(dtype=np.float64))
    best, _, heading = cells.match_among(view, mean, np.arange(6))
    assert best == 2 and abs(heading) == pytest.approx(cells.column_rad, rel=0.25)
    outcome, seen = places.test(np.array([2.2, 0.1, 0.0, 0.1]), view, mean)
    assert outcome == HIT
    np.testing.assert_allclose(seen, [2.0, 0.0, 0.0, 0.0])


@pytest.mark.parametrize(
    ("changes", "faces"),
    [
        ({}, True),  # merge_view_heading (default): the view's column shift
        ({"vt_shift_heading": True}, True),  # the matcher's own offset
        ({"merge_view_heading": False}, False),
        ({"openratslam_compat": True}, False),
    ],
)
def test_a_hits_facing_turns_its_place_by_the_forward_views_heading(changes: dict[str, bool], faces: bool) -> None:
    """``test_faced``: template 2 turned by one column (``camera_fov_deg``/32 = 1.5625°) is a hit at experience 2;
    the place a hypothesis re-anchors on keeps the experience's heading, while where the hit says the robot faced
    (a merge's tie) turns by the view's heading, the column, left of the template for a roll of +1 (the
    shift is −1 column). With the key off, or OpenRatSLAM's behaviour, it is the place."""
    cells = LocalViewCells(PARAMS.replace(**changes))
    cells.add_templates(TEMPLATES, TEMPLATES.reshape(6, -1).mean(axis=1, dtype=np.float64))
    poses = np.array([[float(i), 0.0, 0.0, 0.0] for i in range(6)])
    places = StoredPlaces(cells, poses, np.arange(6), PARAMS.vt_match_threshold, False, RULE)
    view = np.roll(TEMPLATES[2], 1, axis=1)
    outcome, seen, faced = places.test_faced(np.array([2.2, 0.1, 0.0, 0.1]), view, float(view.mean(dtype=np.float64)))
    assert outcome == HIT
    np.testing.assert_allclose(seen, [2.0, 0.0, 0.0, 0.0])
    column = math.radians(PARAMS.camera_fov_deg) / PARAMS.template_x_size
    assert cells.column_rad == pytest.approx(column)
    np.testing.assert_allclose(faced[:3], [2.0, 0.0, 0.0])
    assert faced[3] == pytest.approx(column if faces else 0.0, abs=0.25 * column)
    assert places.test_faced(np.array([2.2, 0.1, 0.0, 0.1]), *_view(-1))[0] == MISS


def test_a_view_whose_best_match_has_no_place_says_nothing() -> None:
    places = _places()
    places.placed[5] = False  # template 5 kept by the stored session's gates without an experience
    assert places.test(np.array([1.0, 0.0, 0.0, 0.0]), *_view(5))[0] == UNMAPPED
    assert places.test(np.array([1.0, 0.0, 0.0, 0.0]), *_view(4))[0] == MISS  # 4 has its place, 3 m away


def test_a_loosely_placed_view_recognised_near_the_prediction_facing_elsewhere_says_nothing() -> None:
    """``sdr-htm`` readers (``loose``): the view's best match is placed 1.2 m from the prediction,
    35° off (outside the facing tolerance, 0.5 rad): no trial; placed 3 m away (beyond the 1.5 m position
    tolerance), or nowhere: a miss, as for LVC, whose strict placing keeps the miss at 1.2 m too."""
    poses = np.array([[0.0, 0.0, 0.0, 0.0], [1.2, 0.0, 0.0, math.radians(35.0)], [3.0, 0.0, 0.0, 0.0]])
    strict = StoredPlaces(_places().cells, poses, np.arange(3), PARAMS.vt_match_threshold, False, RULE)
    loose = StoredPlaces(_places().cells, poses, np.arange(3), PARAMS.vt_match_threshold, False, RULE, loose=True)
    here = np.array([0.0, 0.0, 0.0, 0.0])
    assert strict.test(here, *_view(1))[0] == MISS
    assert loose.test(here, *_view(1))[0] == UNMAPPED
    assert loose.test(here, *_view(2))[0] == MISS  # must still: recognised 3 m away
    assert loose.test(here, *_view(-1))[0] == MISS  # must still: recognised nowhere
    assert loose.test(here, *_view(0))[0] == HIT


def test_hits_at_one_place_re_anchor_once_and_the_robot_is_dead_reckoned_off_it() -> None:
    """Two places, template 0 at x = 0 and template 1 at x = 3; the robot, predicted 0.25 m short of place 0,
    drives east 0.45 m a frame seeing template 0's view throughout (a forward view keeps matching a place's
    template for metres). During a probation the first hit re-anchors the prediction on place 0 (x = 0); the
    next hits there slide it along place 0's heading (east): it follows the odometry's progress (0.45, 0.9)
    but not its drift north (y stays 0 at each hit). At 1.35 m both places lie beyond the coverage radius
    (1 m; no trial), and at 2.25 m place 1 is near: template 0's view there is a miss. Re-anchoring on every
    hit (the code before, and still before a merge and for the loosely placed ``sdr-htm`` views) held the
    prediction on place 0 however far the robot drove: hits every frame."""
    poses = np.array([[0.0, 0.0, 0.0, 0.0], [3.0, 0.0, 0.0, 0.0]])
    places = StoredPlaces(_places().cells, poses, np.arange(2), PARAMS.vt_match_threshold, False, RULE)
    hset, h = HypothesisSet(places, RULE), Hypothesis(alignment=np.array([-0.25, 0.0, 0.0, 0.0]), born=0)
    outcomes, predicted = [], []
    for k, x in enumerate([0.0, 0.45, 0.9, 1.35, 2.25]):
        odometry = np.array([x, 0.02 * k, 0.0, 0.0])  # the odometry drifts 0.02 m north a frame
        outcomes.append(hset._test(h, odometry, *_view(0), 0.45 if k else 0.0, after_merge=True))
        predicted.append(h.predict(odometry)[:2])
    assert outcomes == [HIT, HIT, HIT, UNMAPPED, MISS]
    np.testing.assert_allclose([p[0] for p in predicted], [0.0, 0.45, 0.9, 1.35, 2.25], atol=1e-12)
    np.testing.assert_allclose([p[1] for p in predicted[:3]], 0.0, atol=1e-12)  # slid along place 0's heading
    np.testing.assert_array_equal(h.anchor_place, poses[0])
    assert h.post_hit_m == pytest.approx(0.9) and h.post_miss_m == pytest.approx(0.45)
    h.alignment = np.array([1.0, 0.0, 0.0, 0.0])  # must still: a hit at another place re-anchors there
    assert hset._test(h, np.array([2.25, 0.0, 0.0, 0.0]), *_view(1), 0.5, after_merge=True) == HIT
    np.testing.assert_allclose(h.predict(np.array([2.25, 0.0, 0.0, 0.0])), poses[1], atol=1e-12)
    loose = HypothesisSet(StoredPlaces(places.cells, poses, np.arange(2), PARAMS.vt_match_threshold, False, RULE,
                                       loose=True), RULE)  # fmt: skip
    for pinned, after_merge in ((hset, False), (loose, True)):  # before a merge, and sdr-htm: every hit re-anchors
        before = Hypothesis(alignment=np.array([-0.25, 0.0, 0.0, 0.0]), born=0)
        for k in range(3):
            odometry = np.array([0.45 * k, 0.0, 0.0, 0.0])
            assert pinned._test(before, odometry, *_view(0), 0.45 if k else 0.0, after_merge=after_merge) == HIT
            np.testing.assert_allclose(before.predict(odometry), poses[0], atol=1e-12)


@pytest.mark.parametrize("loose", [True, False])
def test_hits_at_one_loosely_placed_place_count_for_its_extent_and_then_hold(loose: bool) -> None:
    """One place, template 0 at x = 0; the prediction stands on it while the track advances 1 m a frame (a robot
    turning on the spot, say). Loosely placed views (``sdr-htm``): hits at the place count while they span at most
    ``PLACE_EXTENT`` · 1.5 m (frames 1: 1 m), then hold (frames 2 and 3: 2 and 3 m > 1.5 m) — no metres. LVC
    (strict) counts every hit."""
    assert PLACE_EXTENT == 1.0
    places = StoredPlaces(_places().cells, np.zeros((1, 4)), np.arange(1), PARAMS.vt_match_threshold, False, RULE,
                          loose=loose)  # fmt: skip
    hset, h = HypothesisSet(places, RULE), Hypothesis(alignment=np.zeros(4), born=0)
    outcomes = [hset._test(h, np.zeros(4), *_view(0), step, after_merge=True) for step in (0.0, 1.0, 1.0, 1.0)]
    if loose:
        assert outcomes == [HIT, HIT, HELD, HELD] and h.post_hit_m == 1.0
    else:
        assert outcomes == [HIT] * 4 and h.post_hit_m == 3.0  # must still: every hit counts for LVC
    assert h.post_miss_m == 0.0


def test_held_hits_keep_no_metres_before_a_merge_either() -> None:
    """The decision's hypotheses count metres the same way: a held hit adds neither hit metres nor turn."""
    poses = np.array([[0.0, 0.0, 0.0, 0.0]])
    places = StoredPlaces(_places().cells, poses, np.arange(1), PARAMS.vt_match_threshold, True, RULE, loose=True)
    hset, h = HypothesisSet(places, RULE), Hypothesis(alignment=np.zeros(4), born=0)
    outcomes = [hset._test(h, np.array([0.3 * k, 0.0, 0.0, 0.1 * k]), *_view(0), 1.0, after_merge=False)
                for k in range(4)]  # fmt: skip
    assert outcomes == [HIT, HIT, HELD, HELD]  # held 0 and 1 m count; 2 and 3 m > 1.5 m hold
    assert h.hit_m == 2.0 and h.turn_rad == pytest.approx(0.1)  # the held frames' headings (0.2, 0.3) not taken


def _observation(frame: int, odometry: np.ndarray, seen: np.ndarray, template: int) -> Observation:
    return Observation(frame=frame, stored_template=template, stored_experience=template, error=0.0,
                       relative_rad=0.0, partial_template=frame, odometry=odometry, packet=np.zeros(3),
                       seen=seen)  # fmt: skip


def _drive(hset: HypothesisSet, track: Track, start: int, offset: np.ndarray, views: list[int]) -> None:
    """Drive east 1 m a frame from odometry x = start; the stored map sees the robot at ``offset ⊕ O``."""
    for k, v in enumerate(views):
        odometry = np.array([float(start + k), 0.0, 0.0, 0.0])
        track.add(start + k, odometry, 1.0 if track.frames else 0.0, *_view(v))
        seen = compose(offset, odometry)
        found = _observation(start + k, odometry, np.array([float(v), 0, 0, 0]), v) if v >= 0 else None
        hset.update(track, found, v)
        assert np.isfinite(seen).all()


def test_matches_along_the_map_build_one_hypothesis_that_wins_after_the_evidence_distance() -> None:
    hset, track = HypothesisSet(_places(), RULE), Track(RULE.history_m)
    _drive(hset, track, 0, np.zeros(4), [0, 1, 2, 3])
    (h,) = hset.hypotheses
    assert (h.hit_m, h.miss_m, len(h.support), h.stored_templates) == (3.0, 0.0, 4, 4)  # frame 0 moved 0 m
    assert decide({1: hset}, needed=3) is None  # 3 m < 4 m of evidence
    _drive(hset, track, 4, np.zeros(4), [4])
    assert h.score() == 4.0 and h.turn_rad == 0.0
    assert decide({1: hset}, needed=3) is None  # a straight stretch, however long, may be a look-alike street
    h.record_turn(0.6)  # 34°: a look-alike structure can hold such a turn (the twin sweep's false merges: 30–36°)
    assert decide({1: hset}, needed=3) is None
    h.record_turn(0.85)  # the robot turned 49° on agreeing ground (MIN_TURN_RAD: 45°)
    key, winner, rival = decide({1: hset}, needed=3)  # type: ignore[misc]
    assert (key, winner, rival, winner.score()) == (1, h, 0.0, 4.0)


def test_a_look_alike_entered_from_elsewhere_is_refuted_by_the_way_in() -> None:
    """The session saw other views, then stored template 4 one metre ahead of where odometry puts it."""
    hset, track = HypothesisSet(_places(), RULE), Track(RULE.history_m)
    _drive(hset, track, 2, np.zeros(4), [-1])  # no stored map proposed yet: no hypothesis
    assert hset.hypotheses == []
    _drive(hset, track, 3, np.zeros(4), [4])  # proposes A: odometry x=3 is stored x=4
    (h,) = hset.hypotheses
    # the way in (odometry x=2 → stored x=3) is mapped and its view was not template 3: 1 m of misses
    assert (h.hit_m, h.miss_m, h.score()) == (1.0, 1.0, -1.0)
    assert decide({1: hset}, needed=1) is None
    longer, track = HypothesisSet(_places(), RULE), Track(RULE.history_m)
    _drive(longer, track, 0, np.zeros(4), [-1, -1, -1, 4])  # 3 m of mismatches on the way in: 1 − 2·3 < −2·2
    assert longer.hypotheses == []  # refuted at once


def test_two_alignments_that_tie_never_merge_and_one_that_leads_clearly_does() -> None:
    def hset_with(*scores: tuple[float, float]) -> HypothesisSet:
        hset = HypothesisSet(_places(), RULE)
        for i, (hit, miss) in enumerate(scores):
            support = [_observation(j, np.zeros(4), np.zeros(4), j) for j in range(3)]
            hset.hypotheses.append(Hypothesis(np.array([float(i), 0, 0, 0]), born=i, support=support,
                                              hit_m=hit, miss_m=miss, turn=np.array([0.0, 0.0, 1.0])))  # fmt: skip
        return hset

    assert decide({1: hset_with((10.0, 0.0), (10.0, 0.0))}, needed=3) is None  # symmetric world: a tie
    assert decide({1: hset_with((10.0, 0.0)), 2: hset_with((9.0, 0.0))}, needed=3) is None  # across maps too
    assert decide({1: hset_with((10.0, 0.0), (7.9, 0.0))}, needed=3)[2] == 7.9  # type: ignore[index]
    assert decide({1: hset_with((10.0, 0.0), (8.1, 0.0))}, needed=3) is None  # leads by < evidence_m / 2
    assert decide({1: hset_with((10.0, 3.1))}, needed=3) is None  # 10 − 2·3.1 = 3.8 < 4
    assert decide({1: hset_with((10.0, 2.9))}, needed=3) is not None  # 4.2 ≥ 4
    assert decide({1: hset_with((10.0, 0.0))}, needed=4) is None  # K = 4 supporting matches


def test_hypotheses_that_come_to_one_alignment_fold_and_distinct_ones_stay_rivals() -> None:
    """Re-anchoring brought a and b within the 1.5 m tolerance: one alignment; c (3 m) and d (1 rad) differ."""
    hset, track = HypothesisSet(_places(), RULE), Track(RULE.history_m)
    track.add(0, np.array([0.0, 5.0, 0.0, 0.0]), 0.0, *_view(-1))  # unmapped place: no test changes a score
    a = Hypothesis(np.array([0.0, 0.0, 0.0, 0.0]), born=0, hit_m=3.0)
    b = Hypothesis(np.array([1.0, 0.0, 0.0, 0.2]), born=1, hit_m=4.0)
    c = Hypothesis(np.array([3.0, 0.0, 0.0, 0.0]), born=2, hit_m=5.0)
    d = Hypothesis(np.array([0.0, 0.0, 0.0, 1.0]), born=3, hit_m=1.0)
    hset.hypotheses = [a, b, c, d]
    hset.update(track, None)
    assert hset.hypotheses == [b, c, d]  # a folded into b (the better score keeps its evidence)
    assert (b.hit_m, c.hit_m, d.hit_m) == (4.0, 5.0, 1.0)
    tied = HypothesisSet(_places(), RULE)
    tied.hypotheses = [Hypothesis(np.zeros(4), born=5, hit_m=2.0), Hypothesis(np.full(4, 0.1), born=4, hit_m=2.0)]
    tied.update(track, None)
    assert [h.born for h in tied.hypotheses] == [4]  # equal scores: the earliest stays


@settings(max_examples=30, deadline=None)
@given(
    st.lists(st.tuples(st.floats(0, 20), st.floats(0, 20)), min_size=1, max_size=4),
    st.integers(1, 5),
)
def test_the_winner_beats_no_merge_and_every_rival(scores: list[tuple[float, float]], needed: int) -> None:
    hset = HypothesisSet(_places(), RULE)
    for i, (hit, miss) in enumerate(scores):
        support = [_observation(j, np.zeros(4), np.zeros(4), j) for j in range(needed)]
        hset.hypotheses.append(Hypothesis(np.array([float(i), 0, 0, 0]), born=i, support=support, hit_m=hit,
                                          miss_m=miss, turn=np.array([0.0, 0.0, 1.0])))  # fmt: skip
    decision = decide({1: hset}, needed=needed)
    best = max(h.score() for h in hset.hypotheses)
    others = sorted((h.score() for h in hset.hypotheses), reverse=True)[1:]
    clear = best >= RULE.evidence_m and best - max([0.0, *others[:1]]) >= RULE.evidence_m / 2
    assert (decision is not None) == clear  # K matches over distinct templates are there
    if decision is not None:
        assert decision[1].score() == best


def test_the_resume_arrays_hold_hypotheses_bans_and_track_exactly() -> None:
    hset, track = HypothesisSet(_places(), RULE), Track(RULE.history_m)
    _drive(hset, track, 0, np.zeros(4), [0, 1, -1, 3])
    hset.banned.append(np.array([9.0, 1.0, 0.0, 0.5]))
    state = MergerState(np.array([3.0, 0.0, 0.0, 0.0]), (4,), {1: (tuple(hset.hypotheses), tuple(hset.banned))}, track)
    arrays = state.to_arrays()
    again = MergerState.from_arrays(arrays).to_arrays()
    assert set(arrays) == set(again)
    for key in arrays:
        np.testing.assert_array_equal(arrays[key], again[key])
    (h,) = MergerState.from_arrays(arrays).hypotheses[1][0]
    assert (h.hit_m, h.miss_m, [o.frame for o in h.support]) == (hset.hypotheses[0].hit_m,
                                                                  hset.hypotheses[0].miss_m, [0, 1, 3])  # fmt: skip


def test_the_resume_arrays_keep_a_hypothesis_hits_and_read_states_stored_before_them() -> None:
    """The hits a merge ties (``Hypothesis.hits``: odometry and place) come back from the resume arrays, each to
    its hypothesis, in order; a state stored before them loads with none."""
    first = Hypothesis(alignment=np.zeros(4), born=1,
                       hits=[(np.array([1.0, 2.0, 0.0, 0.1]), np.array([5.0, 6.0, 0.0, 0.2])),
                             (np.array([1.5, 2.0, 0.0, 0.1]), np.array([5.5, 6.0, 0.0, 0.2]))])  # fmt: skip
    second = Hypothesis(alignment=np.ones(4), born=2, hits=[(np.array([3.0, 0.0, 0.0, 0.0]), np.zeros(4))])
    arrays = MergerState(np.zeros(4), (), {1: ((first, second), ())}).to_arrays()
    assert arrays["hits"].shape == (3, 9)
    back = MergerState.from_arrays(arrays).hypotheses[1][0]
    for made, original in zip(back, (first, second), strict=True):
        assert len(made.hits) == len(original.hits)
        for (o, p), (o2, p2) in zip(made.hits, original.hits, strict=True):
            np.testing.assert_array_equal(o, o2)
            np.testing.assert_array_equal(p, p2)
    del arrays["hits"]
    assert all(not h.hits for h in MergerState.from_arrays(arrays).hypotheses[1][0])


def test_a_hypothesis_keeps_at_most_max_hits_the_first_and_newest_among_them_and_counts_every_metre() -> None:
    """Past :data:`MAX_HITS` every other hit is dropped, the first and the newest kept; the hit metres still count
    each hit, and below the bound every hit is kept (so the bound alone cannot pass)."""
    h = Hypothesis(alignment=np.zeros(4), born=0)
    for i in range(MAX_HITS):
        h.record_hit(np.array([float(i), 0.0, 0.0, 0.0]), np.array([float(i), 1.0, 0.0, 0.0]), 0.5)
    assert len(h.hits) == MAX_HITS
    assert [float(o[0]) for o, _ in h.hits[:3]] == [0.0, 1.0, 2.0]
    h.record_hit(np.array([float(MAX_HITS), 0.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 0.0]), 0.5)
    kept = [float(o[0]) for o, _ in h.hits]
    assert len(kept) == MAX_HITS // 2 + 1
    assert kept[0] == 0.0 and kept[-1] == float(MAX_HITS)
    assert kept == [float(i) for i in range(0, MAX_HITS + 1, 2)]
    assert h.hit_m == pytest.approx(0.5 * (MAX_HITS + 1))


def test_the_resume_arrays_keep_a_held_place_and_read_states_stored_before_it() -> None:
    """A hypothesis's held place and metres and its anchor place come back from the resume arrays; a state stored
    before they existed (13 or 18 columns a hypothesis) loads with none held or anchored, its other figures as
    stored."""
    h = Hypothesis(alignment=np.array([1.0, 2.0, 0.0, 0.5]), born=4, hit_m=3.0, post_hit_m=1.0,
                   held_place=np.array([5.0, 6.0, 0.0, 0.25]), held_m=1.25,
                   anchor_place=np.array([7.0, 8.0, 0.0, -0.5]))  # fmt: skip
    arrays = MergerState(np.zeros(4), (), {1: ((h,), ())}).to_arrays()
    assert arrays["hypotheses"].shape == (1, 22)
    (back,) = MergerState.from_arrays(arrays).hypotheses[1][0]
    np.testing.assert_array_equal(back.held_place, [5.0, 6.0, 0.0, 0.25])
    np.testing.assert_array_equal(back.anchor_place, [7.0, 8.0, 0.0, -0.5])
    assert back.held_m == 1.25 and back.hit_m == 3.0
    unanchored = {**arrays, "hypotheses": arrays["hypotheses"][:, :18]}  # stored before the anchor place
    (mid,) = MergerState.from_arrays(unanchored).hypotheses[1][0]
    assert mid.anchor_place is None and mid.held_m == 1.25
    before = {**arrays, "hypotheses": arrays["hypotheses"][:, :13]}
    (old,) = MergerState.from_arrays(before).hypotheses[1][0]
    assert old.held_place is None and old.held_m == 0.0 and (old.hit_m, old.post_hit_m, old.born) == (3.0, 1.0, 4)
    np.testing.assert_array_equal(old.alignment, [1.0, 2.0, 0.0, 0.5])

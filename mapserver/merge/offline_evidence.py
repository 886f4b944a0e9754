"""Offline merges weigh their evidence too: a match's alignment tested on every experience of map A.

``mapserver merge --map A --into B`` finds the best confirmed run of A templates matching B
(:func:`mapserver.merge.offline.find_match`, the paper's K-template rule). A look-alike stretch gives
such a run as readily as a true overlap, so, as online (:mod:`mapserver.merge.hypotheses`), the
alignment the run proposes is put to the same sequential test before anything is merged: every
experience of A, moved into B's frame by the alignment, predicts where it lies in B; where B has
been (a stored experience within the coverage radius, facing the same way) A's view there must
match one of B's templates within the position tolerance (a *hit*) or it is a *miss*; unmapped
ground says nothing. The trials are weighted by the distance along A's experience chain (capped at
three spacings, so a jump between A's sessions weighs nothing), and the alignment stands when

    score = hit metres − miss_weight · miss metres ≥ evidence_m   and   the hits span MIN_TURN_RAD,

the online rule's figures (Wald's SPRT over distance; a straight look-alike cannot pin an alignment).
A's whole map is the evidence, before the merge; a look-alike that holds turns passes that test as a true
overlap does (``twin`` with 10–40 m alike: 1–2 of 10 seeds merged two places on that test alone). So the winner also
meets the rule an online merge's probation applies after it (:class:`mapserver.merge.verify.Probation`): along
A's chain after the anchor, in A's own time order, for ``probation_m`` metres and then as long as the matches
go on, no run of ``evidence_m`` metres of misses without a hit between them — and the same along B's chain
after its side of the match, walked against A's places under the inverse alignment (a look-alike's exit shows
on whichever map drove on over mapped ground). And past the far end of the agreement (after each chain's last
hit, the way a probation looks) the two maps must not part in disagreement (:attr:`OfflineEvidence.parting_m`):
when *both* drove on past the same end over each other's ground and both met failing views in a row there before
leaving it, their failing metres add up, and ``evidence_m`` of them rejects. One map's misses past an end are what
drift or the edge of the other map's coverage make (a session driving on past the other map's end; a second lap
dead-reckoned after its last hit: ``symmetric-overlap`` seeds 7 and 9, 6.6–8.6 m, one-sided); both maps driving
on and both disagreeing is how a look-alike stretch ends in two different places (``twin`` with 10 m alike and
turns, seed 6: 2.1 m on A, 3.2 m on B, where every other rule let it merge). The near ends (before the first
hits) are walked backwards from the anchor, away from the match, and are not counted: there a true merge's walks
met stray hits among failing views on both maps (``twin-overlap`` with 60 m alike and turns, seed 9: 2.9 + 2.0 m).

``sdr-htm`` maps (:mod:`mapserver.merge.offline_views`): the trials are A's view cells with a place, in
creation order, and their views are their codes, matched against B's codes and placed as online.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from core.angles import wrap_angle
from core.arrays import BoolArray, FloatArray, IntArray
from core.se3 import alignment, compose, inverse
from mapserver.errors import NoConfirmedMatchError
from mapserver.merge.engines import StoredMap
from mapserver.merge.hypotheses import HIT, MIN_TURN_RAD, MISS, MISS_WEIGHT, EvidenceRule, StoredPlaces
from mapserver.merge.offline import candidate_matches
from mapserver.merge.offline_views import partial_views, stored_views, uses_codes
from mapserver.merge.online import DEFAULT_YAW_TOLERANCE, default_position_tolerance, map_spacing
from mapserver.merge.record import Match
from mapserver.merge.verify import OPEN_PROBATION_CAP, PROBATION_CAP, cap_metres


@dataclass(frozen=True)
class ChainEnd:
    """One end of the agreement along a chain: the failing views past it, and where its outermost hit lies."""

    miss_m: float
    """Metres of failing views in a row along the chain right past this end (before the first hit, after the last)."""
    own: tuple[float, float, float]
    """The outermost hit's position in the chain's own map frame."""
    seen: tuple[float, float, float]
    """Where that hit matched: the other map's place, in the other map's frame."""


@dataclass(frozen=True)
class OfflineEvidence:
    """What A's experiences said of a match's alignment (metres along A's experience chain)."""

    hit_m: float
    miss_m: float
    unmapped_m: float
    turn_rad: float
    evidence_m: float
    miss_weight: float
    hits: int
    misses: int
    agreeing: frozenset[int] = frozenset()
    """A's experiences whose views matched where this alignment (walked, re-anchored) put them."""
    miss_run_m: float = 0.0
    """The longest run of failing views along A's chain with no matching view between them, metres."""
    reverse: OfflineEvidence | None = None
    """The same test the other way: B's chain walked against A's places under the inverse alignment."""
    probation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """What the online probation would have seen after the anchor, along A's chain in its own time order
    (:func:`_probation_window`): (metres walked, longest run of misses, score hit − miss_weight · miss)."""
    closures: tuple[tuple[int, int], ...] = ()
    """(A's experience, B's experience) of every hit: where A's view matched B's template, at B's experience
    nearest the alignment's prediction (LVC maps only: their trials are experiences)."""
    ends: tuple[ChainEnd, ...] = ()
    """The chain's two ends of agreement (before its first hit, after its last), or none without a hit."""

    @property
    def score_m(self) -> float:
        """Return the score: hit metres − miss_weight · miss metres."""
        return self.hit_m - self.miss_weight * self.miss_m

    @property
    def passed(self) -> bool:
        """Whether the alignment stands (evidence 0: the paper's rule, every confirmed match stands)."""
        if self.evidence_m <= 0:
            return True
        held = self.probation_held and (self.reverse is None or self.reverse.probation_held)
        held = held and self.parting_m < self.evidence_m
        return self.score_m >= self.evidence_m and self.turn_rad >= MIN_TURN_RAD and held

    @property
    def parting_m(self) -> float:
        """Return the failing metres both maps met past the far end of their agreement (0 unless both did).

        The far end of a chain's agreement is the end after its last hit, the way a probation looks (after the
        match, in the chain's own time order). This chain's and the other map's (:attr:`reverse`) count when they
        are the same end of the stretch: the other map's last hit lies nearer the place this chain's last hit
        matched than its first hit does (both maps drove the stretch the same way and on past it).
        """
        if self.reverse is None or not self.ends or not self.reverse.ends:
            return 0.0
        mine, theirs = self.ends[1], self.reverse.ends
        seen = np.array(mine.seen)
        same_end = np.linalg.norm(np.array(theirs[1].own) - seen) <= np.linalg.norm(np.array(theirs[0].own) - seen)
        if not same_end or mine.miss_m <= 0.0 or theirs[1].miss_m <= 0.0:
            return 0.0
        return mine.miss_m + theirs[1].miss_m

    @property
    def probation_held(self) -> bool:
        """Whether the probation after the anchor saw no run of ``evidence_m`` metres of misses (the online rule)."""
        return self.probation[1] < self.evidence_m

    def reason(self) -> str:
        """Why the alignment does not stand (empty when it does)."""
        if self.passed:
            return ""
        for side, evidence in (("its own", self), ("the other map's", self.reverse)):
            if evidence is not None and not evidence.probation_held and self.score_m >= self.evidence_m:
                return (
                    f"after the match {side} chain meets {evidence.probation[1]:.1f} m of failing views in a row "
                    f"where the alignment puts them (a probation rejects at {evidence.evidence_m:.1f} m): the "
                    "views matched a look-alike stretch, not the place"
                )
        if self.score_m >= self.evidence_m and self.parting_m >= self.evidence_m:
            return (
                f"where its matching views end, both maps drive on over each other's ground and disagree: "
                f"{self.parting_m:.1f} m of failing views past that end on the two maps together (rejects at "
                f"{self.evidence_m:.1f} m): the views matched a look-alike stretch, not the place"
            )
        if self.score_m < self.evidence_m:
            return (
                f"the rest of the map does not confirm it: {self.hit_m:.1f} m of matching and {self.miss_m:.1f} m "
                f"of failing views where the alignment puts them (score {self.score_m:.1f} m, needs "
                f"{self.evidence_m:.1f} m)"
            )
        return (
            f"its agreeing views span a turn of {np.degrees(self.turn_rad):.0f}° only (needs "
            f"{np.degrees(MIN_TURN_RAD):.0f}°): a straight look-alike stretch cannot pin an alignment"
        )

    def as_dict(self) -> dict[str, Any]:
        """Return the figures for the merge event's ``details.evidence``."""
        return {
            "hit_m": round(self.hit_m, 3), "miss_m": round(self.miss_m, 3), "unmapped_m": round(self.unmapped_m, 3),
            "score_m": round(self.score_m, 3), "turn_deg": round(float(np.degrees(self.turn_rad)), 1),
            "evidence_m": round(self.evidence_m, 3), "hits": self.hits, "misses": self.misses,
            "miss_run_m": round(self.miss_run_m, 3), "passed": self.passed,
            "probation": [round(v, 3) for v in self.probation], "parting_m": round(self.parting_m, 3),
            **({} if self.reverse is None else {"reverse": self.reverse.as_dict()}),
        }  # fmt: skip


def weigh_offline_match(
    partial: StoredMap,
    loaded: StoredMap,
    match: Match,
    *,
    evidence_m: float | None = None,
    position_tolerance: float | None = None,
    yaw_tolerance: float = DEFAULT_YAW_TOLERANCE,
) -> OfflineEvidence:
    """Test the alignment of ``match`` (A's pose of the view → B's experience) on every experience of A.

    Args:
        partial: map A.
        loaded: map B.
        match: the confirmed match :func:`~mapserver.merge.offline.find_match` found.
        evidence_m: metres of net agreement needed (None: A's ``merge_evidence_m``; −1: 4 spacings of B).
        position_tolerance: metres (None: 3 spacings of B).
        yaw_tolerance: radians.
    """
    return _OfflineTest(partial, loaded, evidence_m, position_tolerance, yaw_tolerance).weigh(match)


class _OfflineTest:
    """A's experience chain and B's places, built once for every match weighed between the two maps."""

    def __init__(
        self, partial: StoredMap, loaded: StoredMap, evidence_m: float | None, position_tolerance: float | None,
        yaw_tolerance: float,
    ) -> None:  # fmt: skip
        tolerance = position_tolerance if position_tolerance is not None else default_position_tolerance(loaded)
        spacing = map_spacing(loaded)
        wanted = partial.params.merge_evidence_m if evidence_m is None else evidence_m
        theirs = stored_views(loaded, partial.params, tolerance)  # A's matcher (its gates) over B's views
        miss_weight = getattr(theirs.matcher, "miss_weight", partial.params.miss_weight)
        self.rule = EvidenceRule.for_map(
            spacing, tolerance, yaw_tolerance, wanted, 0.0, miss_weight, partial.params.merge_probation_max_m
        )
        self.probation_m = EvidenceRule.for_map(
            spacing, tolerance, yaw_tolerance, wanted, partial.params.merge_probation_m, miss_weight
        ).probation_m
        p = partial.params
        self.places = StoredPlaces(
            theirs.matcher, theirs.poses, theirs.templates, p.vt_match_threshold, p.vt_panoramic, self.rule,
            loose=theirs.loose,
        )  # fmt: skip
        self.loaded = loaded
        mine = partial_views(partial)
        self.unit_of_view: IntArray | None = None
        """``sdr-htm``: A's view → its trial (−1: none); LVC: None (a match's anchor is its experience)."""
        if uses_codes(partial):  # A's trials are its placed view cells, in creation order
            seen = np.flatnonzero(mine.experiences >= 0)
            self.a_pose, template_of = mine.poses[seen], seen
            self.unit_of_view = np.full(mine.means.shape[0], -1, dtype=np.int64)
            self.unit_of_view[seen] = np.arange(seen.size)
        else:  # A's experiences, each with its template
            self.a_pose = np.asarray(partial.snapshot.map.pose, dtype=np.float64).reshape(-1, 4)
            template_of = np.asarray(partial.snapshot.map.template, dtype=np.int64)
        self.views = (mine.views, mine.means, template_of)
        self.steps = np.zeros(self.a_pose.shape[0])
        if self.a_pose.shape[0] > 1:
            self.steps[1:] = np.linalg.norm(np.diff(self.a_pose[:, :3], axis=0), axis=1)
            self.steps[self.steps > 3.0 * spacing] = 0.0  # a jump between A's sessions is no distance driven

    def anchor(self, match: Match) -> int:
        """Return A's trial where ``match``'s view was seen (the walk starts there): :meth:`unit_of` its view."""
        return self.unit_of(match.partial_template, np.asarray(match.partial_pose, dtype=np.float64))

    def unit_of(self, view: int, pose: FloatArray) -> int:
        """Return this map's trial for its own view ``view`` seen at ``pose`` (its map frame).

        ``sdr-htm``: the view cell itself when it has a place (a match's pose is moved onto the other map's
        experience, off the view cell by that map's place offset); LVC (or a view cell without a place): the
        trial nearest to ``pose`` (an LVC match's pose is its experience's).
        """
        if self.unit_of_view is not None and 0 <= view < self.unit_of_view.size and self.unit_of_view[view] >= 0:
            return int(self.unit_of_view[view])
        return int(np.argmin(np.linalg.norm(self.a_pose[:, :3] - pose[:3], axis=1)))

    def weigh(self, match: Match) -> OfflineEvidence:
        """Walk A's chain both ways from the match's anchor under its alignment; return the evidence."""
        return self.walk(offline_alignment(self.loaded, match), self.anchor(match))

    def walk(self, transform: FloatArray, anchor: int) -> OfflineEvidence:
        """Walk A's chain both ways from its trial ``anchor`` under ``transform`` (A's frame → B's); the evidence."""
        a_pose, steps = self.a_pose, self.steps
        outcomes = np.zeros(a_pose.shape[0], dtype=np.int64)
        seen_at = np.full(a_pose.shape[0], -1, dtype=np.int64)
        seen_pose = np.zeros_like(a_pose)
        for chain in (np.arange(anchor, a_pose.shape[0]), np.arange(anchor, -1, -1)):
            _walk(self.places, transform, a_pose, self.views, chain, outcomes, (seen_at, seen_pose))
        hit, miss = outcomes == HIT, outcomes == MISS
        closures = () if self.unit_of_view is not None else tuple(
            (int(e), int(seen_at[e])) for e in np.flatnonzero(hit & (seen_at >= 0)).tolist()
        )
        turn = 0.0
        if hit.any():
            offsets = wrap_angle(a_pose[hit, 3] - a_pose[hit, 3][0])
            turn = float(np.max(offsets) - np.min(offsets))
        return OfflineEvidence(
            hit_m=float(steps[hit].sum()), miss_m=float(steps[miss].sum()),
            unmapped_m=float(steps[~hit & ~miss].sum()), turn_rad=turn, evidence_m=self.rule.evidence_m,
            miss_weight=self.rule.miss_weight, hits=int(hit.sum()), misses=int(miss.sum()),
            agreeing=frozenset(np.flatnonzero(hit).tolist()), miss_run_m=_longest_miss_run(steps, hit, miss),
            probation=_probation_window(
                steps[anchor + 1 :], outcomes[anchor + 1 :], seen_pose[anchor + 1 :], self.probation_m, self.rule
            ),
            closures=closures, ends=_chain_ends(steps, outcomes, a_pose, seen_pose),
        )  # fmt: skip


def _probation_window(
    steps: FloatArray, outcomes: IntArray, seen: FloatArray, probation_m: float, rule: EvidenceRule
) -> tuple[float, float, float]:
    """Return (metres, longest miss run, score) of A's trials after the anchor that a probation would see.

    As online (:class:`mapserver.merge.verify.Probation`): the probation lasts ``probation_m`` metres and then as
    long as the matches go on (it ends ``evidence_m`` after the newest hit), at most ``OPEN_PROBATION_CAP``
    probation distances until the hit that closes a loop on B (:func:`_loop_closed_at`; ``seen``: each hit's place
    in B), ``PROBATION_CAP`` from then on and always for a front-end with weak misses (``rule.probation_max_m``
    metres when set, at least ``probation_m``) — but not while it is held open
    (:meth:`mapserver.merge.verify.Probation.held_open`): its matches stopped and the miss metres since the newest
    hit (unmapped trials neither add nor break) exceed the coverage radius, more than leaving the map's edge
    explains. Held open, the window runs on until a hit (then ends as before) or the chain's end, so a run of misses
    that an online probation would have met to its rejection is in the window whole. Not for a front-end with weak
    misses (``miss_weight`` below LVC's), as online.
    """
    travelled = np.cumsum(steps)
    hit, miss = outcomes == HIT, outcomes == MISS
    last_hit = np.maximum.accumulate(np.where(hit, travelled, 0.0)) if travelled.size else travelled
    quiet = (travelled >= probation_m) & (travelled - last_hit >= rule.evidence_m)
    held = quiet & (_miss_metres_since_hit(steps, hit, miss) > rule.coverage_radius)
    held &= rule.miss_weight >= MISS_WEIGHT
    cap = np.full(travelled.shape, cap_metres(rule, probation_m, PROBATION_CAP))
    if rule.miss_weight >= MISS_WEIGHT:  # until a loop closes on B, the open cap (weak misses: always the cap)
        open_cap = cap_metres(rule, probation_m, OPEN_PROBATION_CAP)
        within = hit & (travelled < open_cap)  # past the open cap both caps have passed: later hits decide nothing
        cap[travelled < _loop_closed_at(travelled, within, seen, probation_m, rule.position_tolerance)] = open_cap
    over = (quiet | (travelled >= cap)) & ~held
    end = int(np.argmax(over)) + 1 if over.any() else travelled.size
    hit, miss, steps = hit[:end], miss[:end], steps[:end]
    score = float(steps[hit].sum() - rule.miss_weight * steps[miss].sum())
    return (float(steps.sum()), _longest_miss_run(steps, hit, miss), score)


def _loop_closed_at(
    travelled: FloatArray, hit: BoolArray, seen: FloatArray, probation_m: float, tolerance: float
) -> float:
    """Return the metres travelled at the first hit that closes a loop on B (infinity: none does).

    As online (:meth:`mapserver.merge.verify.Probation._note_revisit`): a hit closes a loop when its place in B
    (``seen``) lies within ``tolerance`` of the place of a hit at least ``probation_m`` metres of driving before,
    and a hit in between lay farther than that from it (the chain left the place and came back to it, matching
    at both passes). All hit pairs at once: ``near[i, j]`` for hits i, j; the newest early neighbour of each j
    (memory grows with the square of the hits: the caller passes those within the window's reach only).
    """
    rows = np.flatnonzero(hit)
    if rows.size < 3:
        return float("inf")
    places, metres = seen[rows, :3], travelled[rows]
    near = np.linalg.norm(places[:, None, :] - places[None, :, :], axis=-1) <= tolerance
    early = near & (metres[:, None] <= metres[None, :] - probation_m)  # [i, j]: hit i is j's early neighbour
    newest = np.where(early.any(axis=0), rows.size - 1 - np.argmax(early[::-1], axis=0), -1)
    far = np.cumsum(~near, axis=0)  # [k, j]: hits 0..k farther than the tolerance from j
    columns = np.arange(rows.size)
    before = np.where(newest > 0, far[np.maximum(newest - 1, 0), columns], 0)
    closes = (newest >= 0) & (far[columns, columns] - before > 0)
    return float(metres[np.argmax(closes)]) if closes.any() else float("inf")


def _miss_metres_since_hit(steps: FloatArray, hit: BoolArray, miss: BoolArray) -> FloatArray:
    """Return, at each trial, the miss metres since the newest hit up to it (the online ``miss_run_m``)."""
    missed = np.cumsum(np.where(miss, steps, 0.0))
    at_hit = np.maximum.accumulate(np.where(hit, missed, 0.0)) if missed.size else missed
    return missed - at_hit


def _longest_miss_run(steps: FloatArray, hit: BoolArray, miss: BoolArray) -> float:
    """Return the most miss metres along A's chain between two hits (unmapped trials neither add nor break)."""
    if not miss.any():
        return 0.0
    run = np.cumsum(hit)  # trials between two hits share a run id
    return float(np.bincount(run, weights=np.where(miss, steps, 0.0)).max())


def _chain_ends(steps: FloatArray, outcomes: IntArray, pose: FloatArray, seen: FloatArray) -> tuple[ChainEnd, ...]:
    """Return the chain's two ends of agreement (none without a hit).

    Each: the metres of failing views in a row right past the outermost hit (before the first, after the last; up
    to the first trial that is not a miss: where the chain leaves the other map's ground it has parted from it), the
    outermost hit's own position (``pose``) and where it matched (``seen``, the other map's frame).
    """
    hits = np.flatnonzero(outcomes == HIT)
    if hits.size == 0:
        return ()
    miss = outcomes == MISS
    first, last = int(hits[0]), int(hits[-1])
    past = (_run(steps[:first][::-1], miss[:first][::-1]), _run(steps[last + 1 :], miss[last + 1 :]))
    return tuple(ChainEnd(m, _xyz(pose[e]), _xyz(seen[e])) for m, e in zip(past, (first, last), strict=True))


def _xyz(row: FloatArray) -> tuple[float, float, float]:
    """Return a pose row's position as plain floats."""
    return (float(row[0]), float(row[1]), float(row[2]))


def _run(steps: FloatArray, miss: BoolArray) -> float:
    """Return the metres of the misses in a row at the start of ``miss`` (0 when it starts otherwise)."""
    length = int(np.argmin(miss)) if not miss.all() else miss.size
    return float(steps[:length].sum())


def offline_alignment(loaded: StoredMap, match: Match) -> FloatArray:
    """Return the alignment (4,) taking A's map frame onto B's that ``match`` proposes (Eqs. 13–14)."""
    b_pose = np.asarray(loaded.snapshot.map.pose, dtype=np.float64).reshape(-1, 4)
    seen = compose(b_pose[match.stored_experience], np.array([0.0, 0.0, 0.0, match.relative_rad]))
    return alignment(seen, np.asarray(match.partial_pose, dtype=np.float64))


def _walk(
    places: StoredPlaces,
    transform: FloatArray,
    a_pose: FloatArray,
    views: tuple[np.ndarray, FloatArray, IntArray],
    chain: IntArray,
    outcomes: IntArray,
    record: tuple[IntArray, FloatArray],
) -> None:
    """Test A's experiences along ``chain`` from the anchor, re-anchoring the alignment at every hit.

    As online, where a hypothesis is re-anchored at every agreeing match, the alignment follows the
    drift of A's own map (a bent A is tested locally, not against one rigid alignment of all of it).
    ``record``: each hit's stored place (the row of B's places whose template it matched) and its pose (B's frame).
    """
    seen_at, seen_pose = record
    templates, means, template_of = views
    for e in chain.tolist():
        t = int(template_of[e])
        if not 0 <= t < templates.shape[0]:
            continue
        outcome, seen = places.test(compose(transform, a_pose[e]), templates[t], float(means[t]))
        outcomes[e] = outcome
        if outcome == HIT and seen is not None:
            transform = alignment(seen, a_pose[e])
            seen_at[e], seen_pose[e] = places.row_at(seen), seen


def confirmed_offline_match(
    a: StoredMap, b: StoredMap, confirm: int | None, evidence_m: float | None = None
) -> tuple[Match, OfflineEvidence]:
    """Return the confirmed run of A in B whose alignment the rest of A confirms best (offline evidence test).

    Every confirmed run (best 20) proposes an alignment; each is weighed on A's experiences
    (:func:`weigh_offline_match`). As online (:func:`mapserver.merge.hypotheses.decide`), the winner must
    pass the test and lead every rival by half the evidence distance, a rival being a run whose anchor the
    winner's walk did not find where it predicts it (another place for the same views): two places that
    both fit (a symmetric world) merge neither. The winner is then put to the online probation's run rule on
    both maps (:attr:`OfflineEvidence.probation_held`): A's chain after the anchor, and B's chain after its
    side of the match walked against A's places under the inverse alignment (:attr:`OfflineEvidence.reverse`).

    Raises:
        NoConfirmedMatchError: no confirmed run, none whose alignment stands, or no clear winner.
    """
    candidates = candidate_matches(a, b, confirm=confirm)[:20]
    test = _OfflineTest(a, b, evidence_m, None, DEFAULT_YAW_TOLERANCE)
    weighed = sorted(((test.weigh(m), m) for m in candidates), key=lambda t: -t[0].score_m)
    best, match = weighed[0]
    if best.evidence_m > 0 and best.passed:  # the other way round: B's chain against A's places
        back = _OfflineTest(b, a, evidence_m, None, DEFAULT_YAW_TOLERANCE)
        b_pose = np.asarray(b.snapshot.map.pose, dtype=np.float64).reshape(-1, 4)[match.stored_experience]
        anchor = back.unit_of(match.stored_template, b_pose)
        best = replace(best, reverse=back.walk(inverse(offline_alignment(b, match)), anchor))
    if not best.passed:
        msg = (
            f"{len(candidates)} confirmed run(s) of map {a.key!r} in map {b.key!r}, none whose alignment the rest "
            f"of the map confirms; the best (template {match.partial_template} ↔ {match.stored_template}, "
            f"{match.confirmations} agreeing): {best.reason()}"
        )
        raise NoConfirmedMatchError(msg)
    if best.evidence_m <= 0:  # the paper's rule: the best confirmed run merges, and closes no loop offline
        return match, replace(best, closures=())
    rivals = [ev.score_m for ev, m in weighed[1:] if test.anchor(m) not in best.agreeing]
    lead = best.score_m - max(rivals, default=0.0)
    if lead < 0.5 * best.evidence_m:
        msg = (
            f"map {a.key!r} fits map {b.key!r} under two different alignments (scores {best.score_m:.1f} m and "
            f"{max(rivals):.1f} m, a lead of {lead:.1f} m where {0.5 * best.evidence_m:.1f} m is needed): "
            "look-alike places; not merged"
        )
        raise NoConfirmedMatchError(msg)
    return match, best


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
There is no probation offline: A's whole map is the evidence, before the merge.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from core.localview import LocalViewCells
from core.se3 import alignment, compose, wrap_angle
from mapserver.errors import NoConfirmedMatchError
from mapserver.merge.engines import StoredMap
from mapserver.merge.hypotheses import HIT, MIN_TURN_RAD, MISS, EvidenceRule, StoredPlaces
from mapserver.merge.offline import candidate_matches
from mapserver.merge.online import DEFAULT_YAW_TOLERANCE, default_position_tolerance, map_spacing
from mapserver.merge.record import Match


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

    @property
    def score_m(self) -> float:
        """Return the score: hit metres − miss_weight · miss metres."""
        return self.hit_m - self.miss_weight * self.miss_m

    @property
    def passed(self) -> bool:
        """Whether the alignment stands (evidence 0: the paper's rule, every confirmed match stands)."""
        if self.evidence_m <= 0:
            return True
        return self.score_m >= self.evidence_m and self.turn_rad >= MIN_TURN_RAD

    def reason(self) -> str:
        """Why the alignment does not stand (empty when it does)."""
        if self.passed:
            return ""
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
            "passed": self.passed,
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
        a, b = partial.state, loaded.state
        tolerance = position_tolerance if position_tolerance is not None else default_position_tolerance(loaded)
        spacing = map_spacing(loaded)
        wanted = partial.params.merge_evidence_m if evidence_m is None else evidence_m
        self.rule = EvidenceRule.for_map(spacing, tolerance, yaw_tolerance, wanted, 0.0)
        cells = LocalViewCells.restore(partial.params, b)  # A's matcher over B's templates
        b_pose = np.asarray(b["em_pose"], dtype=np.float64).reshape(-1, 4)
        p = partial.params
        templates = np.asarray(b["em_template"], dtype=np.int64)
        self.places = StoredPlaces(cells, b_pose, templates, p.vt_match_threshold, p.vt_panoramic, self.rule)
        self.loaded = loaded
        self.a_pose = np.asarray(a["em_pose"], dtype=np.float64).reshape(-1, 4)
        self.views = (np.asarray(a["lv_templates"], dtype=np.float32), np.asarray(a["lv_means"], dtype=np.float64),
                      np.asarray(a["em_template"], dtype=np.int64))  # fmt: skip
        self.steps = np.zeros(self.a_pose.shape[0])
        if self.a_pose.shape[0] > 1:
            self.steps[1:] = np.linalg.norm(np.diff(self.a_pose[:, :3], axis=0), axis=1)
            self.steps[self.steps > 3.0 * spacing] = 0.0  # a jump between A's sessions is no distance driven

    def anchor(self, match: Match) -> int:
        """Return A's experience nearest to where ``match``'s view was seen (the walk starts there)."""
        return _anchor_experience(self.a_pose, match)

    def weigh(self, match: Match) -> OfflineEvidence:
        """Walk A's chain both ways from the match's anchor under its alignment; return the evidence."""
        a_pose, steps = self.a_pose, self.steps
        transform = offline_alignment(self.loaded, match)
        outcomes = np.zeros(a_pose.shape[0], dtype=np.int64)
        anchor = self.anchor(match)
        for chain in (np.arange(anchor, a_pose.shape[0]), np.arange(anchor, -1, -1)):
            _walk(self.places, transform, a_pose, self.views, chain, outcomes)
        hit, miss = outcomes == HIT, outcomes == MISS
        turn = 0.0
        if hit.any():
            offsets = wrap_angle(a_pose[hit, 3] - a_pose[hit, 3][0])
            turn = float(np.max(offsets) - np.min(offsets))
        return OfflineEvidence(
            hit_m=float(steps[hit].sum()), miss_m=float(steps[miss].sum()),
            unmapped_m=float(steps[~hit & ~miss].sum()), turn_rad=turn, evidence_m=self.rule.evidence_m,
            miss_weight=self.rule.miss_weight, hits=int(hit.sum()), misses=int(miss.sum()),
            agreeing=frozenset(np.flatnonzero(hit).tolist()),
        )  # fmt: skip


def offline_alignment(loaded: StoredMap, match: Match) -> np.ndarray:
    """Return the alignment (4,) taking A's map frame onto B's that ``match`` proposes (Eqs. 13–14)."""
    b_pose = np.asarray(loaded.state["em_pose"], dtype=np.float64).reshape(-1, 4)
    seen = compose(b_pose[match.stored_experience], np.array([0.0, 0.0, 0.0, match.relative_rad]))
    return alignment(seen, np.asarray(match.partial_pose, dtype=np.float64))


def _anchor_experience(a_pose: np.ndarray, match: Match) -> int:
    """Return A's experience nearest to where the matched view was seen (the walk starts there)."""
    return int(np.argmin(np.linalg.norm(a_pose[:, :3] - np.asarray(match.partial_pose[:3]), axis=1)))


def _walk(
    places: StoredPlaces,
    transform: np.ndarray,
    a_pose: np.ndarray,
    views: tuple[np.ndarray, np.ndarray, np.ndarray],
    chain: np.ndarray,
    outcomes: np.ndarray,
) -> None:
    """Test A's experiences along ``chain`` from the anchor, re-anchoring the alignment at every hit.

    As online, where a hypothesis is re-anchored at every agreeing match, the alignment follows the
    drift of A's own map (a bent A is tested locally, not against one rigid alignment of all of it).
    """
    templates, means, template_of = views
    for e in chain.tolist():
        t = int(template_of[e])
        if not 0 <= t < templates.shape[0]:
            continue
        outcome, seen = places.test(compose(transform, a_pose[e]), templates[t], float(means[t]))
        outcomes[e] = outcome
        if outcome == HIT and seen is not None:
            transform = alignment(seen, a_pose[e])


def confirmed_offline_match(
    a: StoredMap, b: StoredMap, confirm: int | None, evidence_m: float | None = None
) -> tuple[Match, OfflineEvidence]:
    """Return the confirmed run of A in B whose alignment the rest of A confirms best (offline evidence test).

    Every confirmed run (best 20) proposes an alignment; each is weighed on A's experiences
    (:func:`weigh_offline_match`). As online (:func:`mapserver.merge.hypotheses.decide`), the winner must
    pass the test and lead every rival by half the evidence distance, a rival being a run whose anchor the
    winner's walk did not find where it predicts it (another place for the same views): two places that
    both fit (a symmetric world) merge neither.

    Raises:
        NoConfirmedMatchError: no confirmed run, none whose alignment stands, or no clear winner.
    """
    candidates = candidate_matches(a, b, confirm=confirm)[:20]
    test = _OfflineTest(a, b, evidence_m, None, DEFAULT_YAW_TOLERANCE)
    weighed = sorted(((test.weigh(m), m) for m in candidates), key=lambda t: -t[0].score_m)
    best, match = weighed[0]
    if not best.passed:
        msg = (
            f"{len(candidates)} confirmed run(s) of map {a.key!r} in map {b.key!r}, none whose alignment the rest "
            f"of the map confirms; the best (template {match.partial_template} ↔ {match.stored_template}, "
            f"{match.confirmations} agreeing): {best.reason()}"
        )
        raise NoConfirmedMatchError(msg)
    if best.evidence_m <= 0:  # the paper's rule: the best confirmed run merges
        return match, best
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

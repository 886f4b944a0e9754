"""The merge decision: competing alignment hypotheses scored by a sequential test over distance travelled.

A view matching a stored template proposes an alignment ``A = seen ⊕ O⁻¹`` between the running
session's odometry frame (pose ``O`` at that frame) and the stored map (``seen``: the stored
experience of the matched template, turned by the view's heading offset). Look-alike places
propose alignments too, so one match proves nothing. Each distinct alignment becomes a
:class:`Hypothesis`; "no merge" is the implicit hypothesis of score 0.

Every hypothesis predicts, at every frame, where the robot is in the stored map
(``P = A ⊕ O_t``) and therefore what it should see there: the templates of the stored
experiences near ``P`` that face the same way (:class:`StoredPlaces`). Where the stored map
has seen the place, the frame is a Bernoulli trial: the view matches one of the predicted
templates (a *hit*) or none of them (a *miss*); where the stored map has not been, the frame
says nothing. This is the sequential probability ratio test of Wald (1945) over those trials,
with the trials weighted by the distance the robot travelled (frames of a robot standing still
repeat one observation) and a miss weighing ``miss_weight`` hits (log-likelihood ratios
log((1−p₁)/(1−p₀)) ≈ −2.0 and log(p₁/p₀) ≈ 1.3 for p₁ = 0.9, the engine's revisit
recognition, and p₀ = 0.25, a look-alike view matching a predicted place by chance):

    score(h) = hit metres − miss_weight · miss metres.

A new hypothesis is also tested on the frames the session saw *before* it was proposed
(its recent history, :class:`Track`): a look-alike stretch entered from a place that differs
is refuted by what the robot saw on the way in, where the hypothesis says the stored map
was. :func:`decide` merges when one hypothesis clearly beats every other: its score reaches
``evidence_m`` metres, exceeds the best rival (any other alignment, of any stored map, or
"no merge") by half of that, and rests on K supporting matches over two stored templates.

After the merge the same hypothesis keeps being tested during a probation distance
(:mod:`mapserver.merge.verify`).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from core.angles import wrap_angle
from core.arrays import FloatArray, IntArray
from core.localview import LocalViewCells
from core.se3 import alignment, compose, relative
from mapserver.merge.confirm import Observation

if TYPE_CHECKING:
    from mapserver.merge.cortex import CortexReader

MISS_WEIGHT = 2.0
"""A miss on mapped ground outweighs a hit (see the module docstring)."""

MIN_TURN_RAD = math.radians(45.0)
"""The robot's heading must change this much over a winner's hits: a straight look-alike stretch (a street, a
corridor) constrains an alignment along it only as far as it is long, a turn on agreeing ground pins it down.
Measured (``bench/lookalike_sweep.py``, 10 seeds): the false merges of ``twin`` won on hits spanning 30–36°
(the look-alike structure's straight stretch and the ends of its turns), the true ones of ``twin-overlap``
on 66–104°; 30° let 3 of 10 ``twin`` runs merge falsely at 10 m and 20 m stretches, 7 of 10 at 40 m."""

HIT, MISS, UNMAPPED = 1, -1, 0
HELD = 2
"""A loosely placed view's hit at the place the hypothesis already stands on, past that place's extent
(:data:`PLACE_EXTENT`): the views still match there, which keeps a probation open, but they add no metres."""
PLACE_EXTENT = 1.0
"""Metres of hits one place can give a hypothesis in a row, in position tolerances (front-ends that place views
loosely: ``sdr-htm``).

A hit re-anchors the alignment on the place matched (during an LVC probation only the first hit
at a place in a row; later ones slide it along the place: :meth:`HypothesisSet.reanchor`), so where a stretch's
views are all accepted at one place the robot's prediction stays on that place however far it drives, and every
frame is a hit there. Measured on ``twin`` with a 40 m look-alike holding turns (seed 0, ``sdr-htm`` at
``poseidon``'s gate): one view place won every frame of 33 m of the stretch, so a false merge's probation counted
33.5 m of matches, its prediction then lay 33 m behind the robot on ground the stored map never saw (no trials
there), and it passed. A place cannot witness more than the ground it covers, so hits at one place count for this
many position tolerances of travel, and after that hold (:data:`HELD`) until a hit elsewhere. At 1: that merge is
rolled back at the probation's end (2.89 m of matches, 1.97 m of mismatches; at 2 it would pass by 0.02 m)."""


@dataclass(frozen=True)
class EvidenceRule:
    """The distances and tolerances of the test, in metres and radians (resolved for one stored map).

    Attributes:
        evidence_m: net metres of agreement a hypothesis needs to merge (0: K matches suffice).
        probation_m: metres a merge keeps verifying itself after it is applied (0: no verification).
        reject_m: net metres of disagreement that reject a hypothesis (and roll back a merge).
        position_tolerance: metres between a prediction and a match that still agree.
        yaw_tolerance: radians, likewise.
        coverage_radius: a place is mapped when a stored experience lies this close (facing the same way).
        history_m: how far back a new hypothesis is tested against what the session saw.
        miss_weight: a miss counts this many hits.
        max_hypotheses: live hypotheses kept per stored map (the lowest scores go first).
        probation_max_m: metres after which a probation whose matches never stop ends (at least
            ``probation_m``); −1: the front-end's cap (:data:`mapserver.merge.verify.PROBATION_CAP` probation
            distances, :data:`~mapserver.merge.verify.WEAK_MISS_PROBATION_CAP` for weak misses).
    """

    evidence_m: float
    probation_m: float
    reject_m: float
    position_tolerance: float
    yaw_tolerance: float
    coverage_radius: float
    history_m: float
    miss_weight: float = MISS_WEIGHT
    max_hypotheses: int = 8
    probation_max_m: float = -1.0

    @classmethod
    def for_map(
        cls,
        spacing: float,
        position_tolerance: float,
        yaw_tolerance: float,
        evidence_m: float,
        probation_m: float,
        miss_weight: float = MISS_WEIGHT,
        probation_max_m: float = -1.0,
    ) -> EvidenceRule:
        """Resolve the rule for a stored map whose experiences lie ``spacing`` metres apart (median link).

        ``evidence_m``/``probation_m`` of −1 take the map's scale: 4 and 12 experience spacings;
        0 disables the distance rule (K matches merge: the paper with K = 1) or the verification.
        ``probation_max_m``: as given (``Params.merge_probation_max_m``; −1: the front-end's cap).
        """
        evidence = 4.0 * spacing if evidence_m < 0 else float(evidence_m)
        probation = 12.0 * spacing if probation_m < 0 else float(probation_m)
        reject = max(0.5 * evidence, 1.5 * spacing)
        return cls(
            evidence_m=evidence,
            probation_m=probation,
            reject_m=reject,
            position_tolerance=position_tolerance,
            yaw_tolerance=yaw_tolerance,
            coverage_radius=max(spacing, 0.5 * position_tolerance),
            history_m=max(3.0 * evidence, probation, 6.0 * spacing),
            miss_weight=miss_weight,
            probation_max_m=float(probation_max_m),
        )


class Track:
    """The session's recent frames (odometry pose, distance travelled, view), ``keep_m`` metres deep."""

    def __init__(self, keep_m: float) -> None:
        self.keep_m = keep_m
        self.frames: deque[tuple[int, FloatArray, float, np.ndarray, float]] = deque()
        self.distance = 0.0

    def add(self, frame: int, odometry: FloatArray, step_m: float, view: np.ndarray, mean: float) -> None:
        """Append a frame (``step_m``: metres since the previous one) and forget frames beyond ``keep_m``."""
        self.distance += step_m
        self.frames.append((frame, odometry.copy(), self.distance, np.array(view, copy=True), float(mean)))
        while len(self.frames) > 1 and self.distance - self.frames[0][2] > self.keep_m:
            self.frames.popleft()

    @property
    def last(self) -> tuple[int, FloatArray, float, np.ndarray, float]:
        """Return the newest frame (frame, odometry, distance so far, view, mean)."""
        return self.frames[-1]

    def step_of(self, index: int) -> float:
        """Return the metres travelled into frame ``index`` of the window (0 for the oldest)."""
        return 0.0 if index == 0 else self.frames[index][2] - self.frames[index - 1][2]


class StoredPlaces:
    """A stored map as a predictor of views: which templates it expects at a pose.

    Args:
        cells: the stored map's templates with the session's matcher.
        poses: (E, 4) stored experience poses (x, y, z, yaw).
        templates: (E,) each experience's template.
        threshold: the match threshold (the engine's own).
        panoramic: panoramic views match at any heading; forward views only facing the same way.
        rule: the tolerances (:class:`EvidenceRule`).
        loose: the matcher's views are placed loosely (``sdr-htm`` view cells: :meth:`_placed_near`).
    """

    def __init__(
        self,
        cells: LocalViewCells | CortexReader,
        poses: FloatArray,
        templates: IntArray,
        threshold: float,
        panoramic: bool,
        rule: EvidenceRule,
        *,
        loose: bool = False,
    ) -> None:
        self.cells = cells
        self.loose = loose
        self.poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
        self.templates = np.asarray(templates, dtype=np.int64).reshape(-1)
        self.threshold = threshold
        self.panoramic = panoramic
        self.rule = rule
        self._tree = cKDTree(self.poses[:, :3]) if len(self.poses) else None
        self.placed = np.zeros(cells.count, dtype=bool)  # templates with a stored experience (a place)
        self.placed[self.templates[(self.templates >= 0) & (self.templates < cells.count)]] = True

    def row_at(self, pose: FloatArray) -> int:
        """Return the stored place nearest to ``pose`` (its position; −1 when there is none): a hit's place."""
        return -1 if self._tree is None else int(self._tree.query(pose[:3])[1])

    def rows_at(self, poses: FloatArray) -> IntArray:
        """Return :meth:`row_at` for each of ``poses`` (N, 4) at once (−1 each when the map has no place)."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4)
        if self._tree is None:
            return np.full(poses.shape[0], -1, dtype=np.int64)
        return np.asarray(self._tree.query(poses[:, :3])[1], dtype=np.int64).reshape(-1)

    def _near(self, pose: FloatArray, radius: float) -> IntArray:
        """Return the stored experiences within ``radius`` of ``pose`` that face its way (forward views)."""
        if self._tree is None:
            return np.zeros(0, dtype=np.int64)
        near = np.asarray(self._tree.query_ball_point(pose[:3], radius), dtype=np.int64)
        if near.size and not self.panoramic:
            turn = np.abs(wrap_angle(self.poses[near, 3] - pose[3]))
            near = near[turn <= self.rule.yaw_tolerance]
        return np.sort(near)

    def _placed_near(self, template: int, pose: FloatArray) -> bool:
        """Whether a matcher that places its views loosely (``loose``) has ``template`` near ``pose``.

        ``sdr-htm`` view cells sit at their experience plus the odometry since it (:mod:`mapserver.merge.places`),
        from experiences made sparsely (``cave3d`` session 1: 289 cells, 15 experiences): measured on ``cave3d``
        seed 0, a true merge's probation met 5.88 m of mismatches where the frame's SDR matched a view cell made
        0.1 m and 2° from the robot (ground truth) whose place lay 1.0–1.5 m and 30–42° from the prediction,
        outside the facing tolerance. A view recognised that close to the prediction, facing any way, says
        nothing against the alignment: no trial. LVC templates are placed at their experiences: unchanged.
        """
        if not self.loose:
            return False
        mine = np.flatnonzero(self.templates == template)
        gap = np.linalg.norm(self.poses[mine, :3] - pose[:3], axis=1)
        return bool(mine.size and gap.min() <= self.rule.position_tolerance)

    def best_match(self, view: np.ndarray, mean: float) -> int:
        """Return the stored template the view matches best within the threshold (−1: none)."""
        return self.cells.match(view, mean, limit=self.threshold)[0]

    def test_faced(
        self, pose: FloatArray, view: np.ndarray, mean: float, matched: int | None = None
    ) -> tuple[int, FloatArray | None, FloatArray | None]:
        """Return :meth:`test`'s outcome and place, and on a hit where it says the robot faced (:meth:`_view_turn`).

        The facing costs a column search, so only a hit that is recorded asks for it.
        """
        outcome, seen, template, relative = self._trial(pose, view, mean, matched)
        if seen is None:
            return outcome, None, None
        return outcome, seen, compose(seen, np.array([0.0, 0.0, 0.0, self._view_turn(template, view, relative)]))

    def test(
        self, pose: FloatArray, view: np.ndarray, mean: float, matched: int | None = None
    ) -> tuple[int, FloatArray | None]:
        """Return (HIT/MISS/UNMAPPED, where the matched stored place says the robot is (4,) on a hit).

        Mapped: a stored experience within ``coverage_radius`` facing the same way. Hit: the view
        matches (error ≤ threshold) a template of the experiences within ``position_tolerance``.
        Miss: it matches none of them, and its best match in the whole map (``matched``, computed
        when not given) is no template without a place (the stored session's gates keep views
        without making experiences: such a match says nothing about where the robot is), nor, for a
        matcher that places views loosely, one placed within ``position_tolerance`` (:meth:`_placed_near`).

        The place of a hit faces the stored experience's way turned by a panoramic view's offset; a forward
        view's heading (``vt_shift_heading``) is left out: hypotheses re-anchor on every hit, and per-hit
        forward headings turned the alignment 3–27° from hit to hit until a true merge's prediction left
        the stored places (``twin-overlap`` 40 m seed 6, rolled back after 81.6 m of matches). The merge's
        own anchor keeps it (:mod:`mapserver.merge.online`); a merge's ties take the view's heading
        (:meth:`test_faced`).
        """
        outcome, seen, _, _ = self._trial(pose, view, mean, matched)
        return outcome, seen

    def _trial(
        self, pose: FloatArray, view: np.ndarray, mean: float, matched: int | None
    ) -> tuple[int, FloatArray | None, int, float]:
        """Return :meth:`test`'s outcome and place, the stored template hit (−1) and the match's offset."""
        if self._near(pose, self.rule.coverage_radius).size == 0:
            return UNMAPPED, None, -1, 0.0
        near = self._near(pose, self.rule.position_tolerance)
        u, _error, relative = self.cells.match_among(view, mean, self.templates[near], limit=self.threshold)
        if u < 0:
            best = self.best_match(view, mean) if matched is None else matched
            if best >= 0 and (not self.placed[best] or self._placed_near(best, pose)):
                return UNMAPPED, None, -1, 0.0
            return MISS, None, -1, 0.0
        mine = near[self.templates[near] == u]
        closest = mine[int(np.argmin(np.linalg.norm(self.poses[mine, :3] - pose[:3], axis=1)))]
        turn = relative if self.panoramic else 0.0  # a forward view's heading (vt_shift_heading) jitters per hit
        return HIT, compose(self.poses[closest], np.array([0.0, 0.0, 0.0, turn])), u, relative

    def _view_turn(self, template: int, view: np.ndarray, relative: float) -> float:
        """Return a forward view's heading against the stored ``template`` it hit (``merge_view_heading``; else 0).

        ``vt_shift_heading``'s offset when the matcher gives one, else the view's column shift
        (``LocalViewCells.view_heading``); 0 for panoramic views (the place already faces their offset) and for
        matchers without columns (``sdr-htm`` readers).
        """
        params = getattr(self.cells, "params", None)
        if self.panoramic or params is None or not params.merge_view_heading or params.openratslam_compat:
            return 0.0
        if params.vt_shift_heading:
            return relative
        heading = getattr(self.cells, "view_heading", None)
        return 0.0 if heading is None else float(heading(template, view))


MAX_HITS = 4096
"""Hits one hypothesis keeps (:attr:`Hypothesis.hits`, each a merge tie if it wins). Past it every other one is
dropped, first and newest kept: the span stays, the density halves. A hypothesis that keeps matching for kilometres
without winning would otherwise grow its list, the resume arrays and its merge's ties for as long as it lives; at
the simulator's 0.5 m per frame the bound is 2 km of hits, and no merge measured has had more than a few hundred."""


@dataclass(eq=False)
class Hypothesis:
    """One candidate alignment of the session's odometry frame with a stored map, and its evidence.

    Attributes:
        alignment: (4,) odometry frame → stored map frame, re-anchored at every agreeing match
            (so that odometry drift since the proposal does not accumulate).
        born: the frame that proposed it.
        support: the matches that agreed with it (the merge's anchor and template pairs).
        hit_m, miss_m: metres of hits and misses before the merge (history included).
        post_hit_m, post_miss_m: the same after the merge (probation).
    """

    alignment: FloatArray
    born: int
    support: list[Observation] = field(default_factory=list)
    hit_m: float = 0.0
    miss_m: float = 0.0
    post_hit_m: float = 0.0
    post_miss_m: float = 0.0
    turn: FloatArray = field(default_factory=lambda: np.array([np.nan, 0.0, 0.0]))
    """Odometry heading of the first hit, and the least and greatest heading of the hits relative to it."""
    held_place: FloatArray | None = None
    """The place (4,) of the newest hit (loosely placed views; None: none yet)."""
    held_m: float = 0.0
    """Metres of hits at ``held_place`` since a hit elsewhere (:data:`PLACE_EXTENT`)."""
    anchor_place: FloatArray | None = None
    """The stored place (4,) the alignment was last re-anchored on by a hit (:meth:`HypothesisSet.reanchor`)."""
    hits: list[tuple[FloatArray, FloatArray]] = field(default_factory=list)
    """(odometry, stored place) of every hit before the merge, history included: where a view put the robot, facing
    the way the view says (:meth:`StoredPlaces.test_faced`)."""

    def record_hit(self, odometry: FloatArray, seen: FloatArray, metres: float) -> None:
        """Count a hit before the merge: its metres, the heading it was seen at, and where it put the robot.

        At most :data:`MAX_HITS` hits are kept.
        """
        self.hit_m += metres
        self.record_turn(float(odometry[3]))
        self.hits.append((odometry.copy(), np.array(seen, dtype=np.float64)))
        if len(self.hits) > MAX_HITS:
            self.hits = self.hits[::2]

    def record_turn(self, yaw: float) -> None:
        """Widen the span of headings the hits were seen at."""
        if np.isnan(self.turn[0]):
            self.turn[0] = yaw
        offset = float(wrap_angle(yaw - self.turn[0]))
        self.turn[1], self.turn[2] = min(self.turn[1], offset), max(self.turn[2], offset)

    @property
    def turn_rad(self) -> float:
        """Return how far the robot's heading turned over the hits (radians)."""
        return float(self.turn[2] - self.turn[1])

    def score(self, miss_weight: float = MISS_WEIGHT) -> float:
        """Return the pre-merge score: hit metres − miss_weight · miss metres (Wald's log-likelihood ratio)."""
        return self.hit_m - miss_weight * self.miss_m

    def predict(self, odometry: FloatArray) -> FloatArray:
        """Return where this alignment puts the robot in the stored map: ``A ⊕ O``."""
        return compose(self.alignment, odometry)

    def agrees(self, observation: Observation, rule: EvidenceRule) -> bool:
        """Return whether a match lies where this hypothesis predicts it (position and heading tolerances)."""
        predicted = self.predict(observation.odometry)
        gap = float(np.linalg.norm(predicted[:3] - observation.seen[:3]))
        turn = abs(float(wrap_angle(predicted[3] - observation.seen[3])))
        return gap <= rule.position_tolerance and turn <= rule.yaw_tolerance

    @property
    def anchor(self) -> Observation:
        """Return the best-matching supporting frame (lowest error, the latest on ties): the merge anchor."""
        return min(reversed(self.support), key=lambda o: o.error)

    @property
    def stored_templates(self) -> int:
        """Return how many distinct stored templates support it."""
        return len({o.stored_template for o in self.support})

    def pairs(self) -> tuple[tuple[int, int], ...]:
        """Return the (session template, stored template) pairs of its support, in frame order."""
        return tuple((o.partial_template, o.stored_template) for o in sorted(self.support, key=lambda o: o.frame))

    def evidence(self, rule: EvidenceRule) -> dict[str, float | int]:
        """Return the figures a merge event stores about this hypothesis."""
        return {
            "hit_m": round(self.hit_m, 3), "miss_m": round(self.miss_m, 3),
            "score_m": round(self.score(rule.miss_weight), 3),
            "support": len(self.support), "stored_templates": self.stored_templates, "born_frame": self.born,
            "post_hit_m": round(self.post_hit_m, 3), "post_miss_m": round(self.post_miss_m, 3),
            "turn_deg": round(math.degrees(self.turn_rad), 1),
        }  # fmt: skip


class HypothesisSet:
    """The competing alignments of the running session with one stored map (see the module docstring)."""

    def __init__(self, places: StoredPlaces, rule: EvidenceRule) -> None:
        self.places = places
        self.rule = rule
        self.hypotheses: list[Hypothesis] = []
        self.banned: list[FloatArray] = []  # alignments rolled back by their verification

    def update(self, track: Track, observation: Observation | None, matched: int = -1) -> None:
        """Test every hypothesis on the newest frame of ``track``, then add the frame's match.

        A match that agrees with a hypothesis supports it (and re-anchors it); one that agrees
        with none proposes a new hypothesis, first tested on the track's earlier frames.
        """
        frame, odometry, _, view, mean = track.last
        step = track.step_of(len(track.frames) - 1)
        for hypothesis in self.hypotheses:
            self._test(hypothesis, odometry, view, mean, step, after_merge=False, matched=matched)
        if observation is None or not observation.has_geometry:
            self._fold(odometry)
            return
        agreeing = [h for h in self.hypotheses if h.agrees(observation, self.rule)]
        for hypothesis in agreeing:
            hypothesis.support.append(observation)
            hypothesis.alignment, hypothesis.anchor_place = observation.alignment, None
        if agreeing or self._is_banned(observation):
            self._fold(odometry)
            return
        born = Hypothesis(alignment=observation.alignment, born=frame, support=[observation])
        if self.rule.evidence_m > 0:  # 0: the paper's decision on matches alone
            self._test_history(born, track)
        self._test(born, odometry, view, mean, step, after_merge=False, matched=matched)
        self.hypotheses.append(born)
        self._prune()

    def _fold(self, odometry: FloatArray) -> None:
        """Fold hypotheses that now put the robot at the same place (within the tolerances) into the best one.

        Re-anchoring at every hit can bring two hypotheses born apart onto one alignment: they are then one
        candidate alignment, not rivals; the best-scoring keeps its evidence (the earliest on ties), the
        others go (their evidence counted the same frames).
        """
        if len(self.hypotheses) < 2:
            return
        rule = self.rule
        ranked = sorted(self.hypotheses, key=lambda h: (-h.score(rule.miss_weight), h.born))
        kept: list[tuple[Hypothesis, FloatArray]] = []
        for hypothesis in ranked:
            p = hypothesis.predict(odometry)
            if not any(
                np.linalg.norm(p[:3] - q[:3]) <= rule.position_tolerance
                and abs(float(wrap_angle(p[3] - q[3]))) <= rule.yaw_tolerance
                for _, q in kept
            ):
                kept.append((hypothesis, p))
        survivors = {id(h) for h, _ in kept}
        self.hypotheses = [h for h in self.hypotheses if id(h) in survivors]

    def _test(
        self,
        hypothesis: Hypothesis,
        odometry: FloatArray,
        view: np.ndarray,
        mean: float,
        step: float,
        after_merge: bool,
        matched: int | None = None,
    ) -> int:
        predicted = hypothesis.predict(odometry)
        if after_merge:  # a probation's hit records no place
            outcome, seen, faced = *self.places.test(predicted, view, mean, matched), None
        else:
            outcome, seen, faced = self.places.test_faced(predicted, view, mean, matched)
        if outcome == HIT:
            assert seen is not None  # a hit has a place
            if self.places.loose and self._held(hypothesis, seen, step):
                self.reanchor(hypothesis, seen, odometry, once=False)
                return HELD
            if after_merge:
                hypothesis.post_hit_m += step
            else:
                assert faced is not None  # a hit has a place
                hypothesis.record_hit(odometry, faced, step)
            self.reanchor(hypothesis, seen, odometry, once=after_merge and not self.places.loose)
        elif outcome == MISS:
            if after_merge:
                hypothesis.post_miss_m += step
            else:
                hypothesis.miss_m += step
        return outcome

    @staticmethod
    def reanchor(hypothesis: Hypothesis, seen: FloatArray, odometry: FloatArray, once: bool = True) -> None:
        """Re-anchor the alignment on a hit's place; with ``once``, only on the first hit at that place in a row.

        A hit says the robot is near ``seen``; the alignment is set so that it predicts the robot there
        (``A = seen ⊖ O``), which keeps odometry drift from accumulating. A forward view keeps matching one
        place's template while the robot drives on for metres, though, and re-anchoring on every such hit
        pinned the prediction to that place while the robot left it. Traced on ``twin-overlap`` turns
        alike 40 m (seed 2, ``circle``): a true merge's prediction followed the robot within 1 m for 83 m,
        then hits at the stored map's last places held it there while the robot drove 8 m on, and the run of
        mismatches that followed rolled the merge back. So during an LVC probation (``once``) a hit at the place
        the alignment last re-anchored on slides the prediction along that place's heading: its heading and its
        offset across the place's line are the place's, its progress along the line is dead-reckoned (the robot
        drives on the way the view looks). Dead-reckoned in full instead, a false merge's prediction left the
        stored places sideways (``symmetric`` seed 8: rolled back 31 frames later, the true merge then 10 frames
        later and its map 1.25 → 1.91× the single route). Before a merge every hit re-anchors, as the decision
        was measured; so does every hit of a front-end that places its views loosely (``sdr-htm``), whose
        probation holds a place's hits after its extent instead (:data:`PLACE_EXTENT`): dead-reckoned on,
        ``neoslam``'s false merge of ``twin`` turns alike 20 m (seed 0) passed its probation.
        """
        if once and hypothesis.anchor_place is not None and np.array_equal(seen, hypothesis.anchor_place):
            ahead = float(relative(seen, hypothesis.predict(odometry))[0])  # progress along the place's heading
            hypothesis.alignment = alignment(compose(seen, np.array([ahead, 0.0, 0.0, 0.0])), odometry)
            return
        hypothesis.alignment = alignment(seen, odometry)
        hypothesis.anchor_place = np.array(seen, dtype=np.float64)

    def _held(self, hypothesis: Hypothesis, seen: FloatArray, step: float) -> bool:
        """Whether a hit at ``seen`` is past its place's extent (:data:`PLACE_EXTENT`).

        Past it: hits there in a row, since one elsewhere, have covered more than ``PLACE_EXTENT`` position
        tolerances (this hit's ``step`` included).
        """
        if hypothesis.held_place is not None and np.array_equal(seen, hypothesis.held_place):
            hypothesis.held_m += step
        else:
            hypothesis.held_place, hypothesis.held_m = np.array(seen, dtype=np.float64), 0.0
        return hypothesis.held_m > PLACE_EXTENT * self.rule.position_tolerance

    def _test_history(self, hypothesis: Hypothesis, track: Track) -> None:
        """Test a new hypothesis on the frames before it, at most one per quarter coverage radius travelled."""
        frames = list(track.frames)[:-1]
        if not frames:
            return
        spacing = 0.25 * self.rule.coverage_radius
        newest = frames[-1][2]
        last_tested = -np.inf
        for i in range(len(frames) - 1, -1, -1):
            _frame, odometry, travelled, view, mean = frames[i]
            if newest - travelled > self.rule.history_m:
                break
            if last_tested - travelled < spacing and np.isfinite(last_tested):
                continue
            weight = (last_tested if np.isfinite(last_tested) else track.last[2]) - travelled
            outcome, _, faced = self.places.test_faced(hypothesis.predict(odometry), view, mean)
            if outcome == HIT:
                assert faced is not None  # a hit has a place
                hypothesis.record_hit(odometry, faced, weight)
            elif outcome == MISS:
                hypothesis.miss_m += weight
            last_tested = travelled

    def test_after_merge(self, hypothesis: Hypothesis, track: Track) -> int:
        """Test the merged hypothesis on the newest frame (probation); return HIT, MISS, UNMAPPED or HELD."""
        _frame, odometry, _, view, mean = track.last
        return self._test(hypothesis, odometry, view, mean, track.step_of(len(track.frames) - 1), after_merge=True)

    def _is_banned(self, observation: Observation) -> bool:
        for banned in self.banned:
            predicted = compose(banned, observation.odometry)
            if np.linalg.norm(predicted[:3] - observation.seen[:3]) <= self.rule.position_tolerance:
                return True
        return False

    def ban(self, hypothesis: Hypothesis) -> None:
        """Never propose this alignment again (its merge was rolled back)."""
        self.banned.append(hypothesis.alignment.copy())
        self.hypotheses = [h for h in self.hypotheses if h is not hypothesis]

    def _prune(self) -> None:
        """Drop refuted hypotheses and keep the ``max_hypotheses`` best."""
        rule = self.rule
        floor = -2.0 * rule.reject_m if rule.evidence_m > 0 else -np.inf
        alive = [h for h in self.hypotheses if h.score(rule.miss_weight) > floor]
        alive.sort(key=lambda h: (-h.score(rule.miss_weight), h.born))
        self.hypotheses = alive[: rule.max_hypotheses]

    def best(self) -> Hypothesis | None:
        """Return the highest-scoring hypothesis (the earliest on ties), or None."""
        if not self.hypotheses:
            return None
        return max(self.hypotheses, key=lambda h: (h.score(self.rule.miss_weight), -h.born))


def decide(sets: dict[object, HypothesisSet], needed: int) -> tuple[object, Hypothesis, float] | None:
    """Return (stored map key, winning hypothesis, best rival score) when one hypothesis clearly wins.

    It wins when its score reaches its map's ``evidence_m``, beats the best rival (every other
    hypothesis of every stored map, and "no merge" at 0) by half of ``evidence_m``, its hits were seen
    while the robot turned by :data:`MIN_TURN_RAD` at least, and it rests on ``needed`` (K) supporting
    matches over at least two stored templates when K ≥ 2. With ``evidence_m`` = 0 the matches alone decide.
    """
    ranked: list[tuple[float, object, Hypothesis]] = []
    for key, hset in sets.items():
        ranked.extend((h.score(hset.rule.miss_weight), key, h) for h in hset.hypotheses)
    if not ranked:
        return None
    ranked.sort(key=lambda r: (-r[0], r[2].born))
    score, key, winner = ranked[0]
    rival = max(0.0, ranked[1][0]) if len(ranked) > 1 else 0.0
    rule = sets[key].rule
    if len(winner.support) < needed or (needed >= 2 and winner.stored_templates < 2):
        return None
    if rule.evidence_m > 0 and (
        score < rule.evidence_m or score - rival < 0.5 * rule.evidence_m or winner.turn_rad < MIN_TURN_RAD
    ):
        return None
    return key, winner, rival

"""The online merge driver: fed after every frame of a session, it merges the session into stored maps.

Usage (what ``pipeline.py`` does)::

    merger = OnlineMerger([StoredMap(key, params, state), ...])
    engine = Engine(params, origin=tag)   # the session's origin tag (the store: its id, or 0 until it has one)
    for frame in frames:
        result = engine.step(frame.image, frame.motion, frame.stamp_ns * 1e-9)
        event = merger.observe(engine, result, frame)
        if isinstance(event, MergeEvent):   # a merge: continue in the merged engine
            engine = event.engine
        elif isinstance(event, Rollback):   # its verification failed: continue as the session's own map
            engine = event.engine

After every frame the current view (``engine.local_view.last_view``) is matched against
every candidate stored map's templates with the engine's own matcher
(``LocalViewCells.match`` with the match threshold as its limit). Matches propose alignments;
the merge decision weighs them as competing hypotheses with a sequential test over distance
travelled (:mod:`mapserver.merge.hypotheses`): a merge needs one alignment to clearly beat all
others and "no merge" over ``merge_evidence_m`` metres. Then the session's engine is merged
into that map (:func:`mapserver.merge.engines.merge_engine`), mapping continues in the merged
engine, and the merge verifies itself for ``merge_probation_m`` metres
(:mod:`mapserver.merge.verify`); a contradiction rolls it back (:class:`Rollback`). No other
merge is decided during a probation. The session may later merge into another stored map: the
merged engine (session plus the first map) is then the partial map and the second map the
loaded one, so one session bridging two maps joins them into one.

Known start (Menezes et al. scenario i): a session that starts at a mapped place wins its
hypothesis after ``merge_evidence_m`` metres; every template it made by then is paired with a
stored one (the hypothesis's support), so the merge identifies them and no separate partial
map remains.

Resume: :meth:`OnlineMerger.export_state` returns what the driver carries from frame to frame
(the session's odometry, the maps absorbed, the recent track, the hypotheses) as a
:class:`MergerState`; ``OnlineMerger(..., resume=state)`` continues from it, so a session
stopped after frame k and continued gives the merges of one run. ``process --stop-after`` runs on
past k while a probation runs (``mapserver.processing.run.run_engine``'s ``overrun``), so a stored merge is
always verified; a probation still running when the log ends is judged there on what it saw
(:meth:`OnlineMerger.finish`): its merge stays when the probation's own evidence confirms it, and is
rolled back otherwise.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from scipy.spatial import cKDTree

from core import Engine, LinkKind, Params, StepResult
from core.arrays import FloatArray, IntArray, UInt8Array
from core.localview import LocalViewCells
from core.se3 import compose, relative
from core.snapshot import ExperienceMapSnapshot
from mapserver.merge.confirm import Observation
from mapserver.merge.engines import StoredMap, merge_engine
from mapserver.merge.hypotheses import EvidenceRule, Hypothesis, HypothesisSet, StoredPlaces, Track, decide
from mapserver.merge.places import template_places
from mapserver.merge.record import Match, MergeRecord
from mapserver.merge.resume import MergerState
from mapserver.merge.snapshot import experiences_by_template, params_incompatibility
from mapserver.merge.verify import LAZY_SHADOW_BYTES, PASSED, REJECTED, Probation, SessionFrame, image_bytes

if TYPE_CHECKING:
    from core.neocortex import NeocortexViewCells
    from mapserver.merge.cortex import CortexReader

logger = logging.getLogger(__name__)

TIE_HITS = True
"""Whether a merge ties the session's own copy of the stored ground to it by a merge link per hit of the winner
(:meth:`OnlineMerger._ties`, :attr:`Match.ties`); off, the anchor (and the identified experiences) alone join
the graphs, as before 2026-11-29 (tests switch it off to show what the ties hold)."""

DEFAULT_YAW_TOLERANCE = 0.5
"""Radians between a match's heading and the heading a hypothesis predicts."""


@dataclass(frozen=True, eq=False)
class MergeEvent:
    """One merge made by the online driver.

    Attributes:
        key: the stored map merged into (the loaded map).
        engine: the merged engine; the session continues in it.
        record: what the merge did (:class:`MergeRecord`).
        frame: the session frame that decided the merge.
        stamp: its log time (s).
        absorbed: keys of stored maps already merged into the session before this merge
            (they are part of the partial map here).
        match: the correspondence the merge applied (re-applying it to the same two states
            gives the same merged state: redo).
        partial: the session's engine snapshot right before the merge (the partial map; an
            undo restores it).
        odometry: (4,) the driver's odometry pose of the session at the frame (x, y, z, yaw).
        session_pose: (4,) the robot's pose in the session's own map frame right before the merge (its
            experience map's ``robot_pose``): the merge puts the robot at ``T ⊕ session_pose``. It differs from
            the dead reckoning once the session's map has closed a loop.
        evidence: the decision's figures (the winner's hits and misses, the best rival's score,
            the rule) and, once known, ``verification`` (:meth:`Probation.evidence`).
    """

    key: object
    engine: Engine
    record: MergeRecord
    frame: int
    stamp: float
    absorbed: tuple[object, ...] = ()
    match: Match | None = None
    partial: Mapping[str, np.ndarray] | None = field(default=None, repr=False)
    odometry: FloatArray | None = field(default=None, repr=False)
    evidence: dict[str, Any] = field(default_factory=dict, repr=False)
    session_pose: FloatArray | None = field(default=None, repr=False)


@dataclass(frozen=True, eq=False)
class Rollback:
    """A merge rolled back by its own verification: the session continues in ``engine`` (its own map).

    Attributes:
        event: the merge rolled back (its ``evidence["verification"]`` says why).
        engine: the session's engine as if the merge had never happened.
        frame: the frame that contradicted the merge.
        created: experiences ``engine`` made during the probation: (id, stamp, camera image).
        seen: ``engine``'s active template at each probation frame: (stamp, template, created).
    """

    event: MergeEvent
    engine: Engine
    frame: int
    created: tuple[tuple[int, float, UInt8Array], ...] = field(default=(), repr=False)
    seen: tuple[tuple[float, int, bool], ...] = field(default=(), repr=False)


@dataclass(frozen=True, eq=False)
class _Unread:
    """A frame the ``sdr-htm`` readers have not read yet: its packed SDR, read when a merge, resume or rollback asks."""

    code: UInt8Array


@dataclass(eq=False)
class _Candidate:
    stored: StoredMap
    cells: LocalViewCells | CortexReader  # CortexReader for sdr-htm maps
    order: IntArray
    starts: IntArray
    hypotheses: HypothesisSet
    anchors: IntArray
    """Per place of ``hypotheses.places``: the stored experience a merge anchors on (places are the
    experiences, and for sdr-htm maps also the view cells' places, :mod:`mapserver.merge.places`)."""


def map_spacing(stored: StoredMap) -> float:
    """Return the median odometry-link length of a stored map (its experience spacing), metres.

    A map without links falls back to the experience threshold in metres.
    """
    kind = np.asarray(stored.snapshot.map.link_kind)
    distance = np.asarray(stored.snapshot.map.link_distance, dtype=np.float64)[kind == LinkKind.ODOMETRY]
    distance = distance[distance > 0]
    p = stored.params
    floor = p.exp_delta_pc_threshold * p.pc_cell_x_size
    return floor if distance.size == 0 else max(float(np.median(distance)), 0.25 * floor)


def default_position_tolerance(stored: StoredMap) -> float:
    """Return 3× the experience spacing of a stored map (:func:`map_spacing`), metres.

    A view matches a template over about one experience spacing, so agreeing matches may
    differ by that much.
    """
    return 3.0 * map_spacing(stored)


class OnlineMerger:
    """Merges a running session into the stored maps it connects to (see the module docstring).

    Args:
        stored: the candidate stored maps (maps whose parameters cannot merge with the
            session's are skipped, see :attr:`skipped`).
        confirm: K, supporting matches a winning hypothesis needs; None → ``Params.merge_confirm``.
        shift_lattice: False disables operation (iii) (debug, the paper's Fig. 12).
        position_tolerance: metres; None → :func:`default_position_tolerance` per map.
        yaw_tolerance: radians (default :data:`DEFAULT_YAW_TOLERANCE`).
        resume: the driver's state after an earlier part of the same session
            (:meth:`export_state`); hypotheses of maps not among ``stored`` are ignored.
        evidence_m, probation_m: metres (None → ``Params.merge_evidence_m`` / ``merge_probation_m``;
            −1 → the stored map's scale; 0 → K matches decide / no verification).
    """

    def __init__(
        self,
        stored: Sequence[StoredMap],
        *,
        confirm: int | None = None,
        shift_lattice: bool = True,
        position_tolerance: float | None = None,
        yaw_tolerance: float = DEFAULT_YAW_TOLERANCE,
        resume: MergerState | None = None,
        evidence_m: float | None = None,
        probation_m: float | None = None,
    ) -> None:
        self._stored = list(stored)
        self._confirm = confirm
        self.shift_lattice = shift_lattice
        self._position_tolerance = position_tolerance
        self._yaw_tolerance = yaw_tolerance
        self._evidence_m = evidence_m
        self._probation_m = probation_m
        self._candidates: list[_Candidate] | None = None
        self._readers: list[CortexReader] = []
        """sdr-htm maps: every prepared candidate's :class:`mapserver.merge.cortex.CortexReader` (rows of the views)."""
        self._unread: list[tuple[SessionFrame, _Unread, int, bool]] = []
        """Frames the readers have not read yet (frame, its code, the session's view cell, made there)."""
        self._unread_bytes = 0
        self._before_merge: list[_Candidate] = []
        self.skipped: dict[object, str] = {}
        self.absorbed: list[object] = []
        self.observed: set[object] = set()
        """Keys of the stored maps a frame's view matched (or that were merged into): the maps whose changes
        can change this session's decisions (:mod:`mapserver.merge.relevance`)."""
        self.events: list[MergeEvent] = []
        self.rollbacks: list[Rollback] = []
        self.probation: Probation | None = None
        self._probation_event: MergeEvent | None = None
        # The driver's odometry (x, y, z, yaw): a frame of its own, not the session's dead reckoning
        # (mapserver.processing.reckoning.DeadReckoning, integrated by run_engine). It starts at the identity when the
        # merger starts (or at its stored state on resume), wraps the heading (core.se3.compose) and is kept
        # with the merger's state; the dead reckoning starts at the preset's initial heading, sums the heading
        # unwrapped (core.se3.compose_step) and goes on across resumes. The hypotheses' predictions and
        # stored merge records are in this frame, so it is integrated here (:meth:`observe`).
        self._odometry = np.zeros(4)
        self._track = Track(0.0)
        self._resume: MergerState | None = resume
        if resume is not None:
            self._odometry = np.asarray(resume.odometry, dtype=np.float64).copy()
            self.absorbed = list(resume.absorbed)

    @property
    def sdr_gates(self) -> dict[object, float]:
        """Return each ``sdr-htm`` candidate map's code gate θ (``CortexReader.min_overlap``) by map key."""
        return {reader.key: reader.min_overlap for reader in self._readers}

    @property
    def candidates(self) -> list[object]:
        """Return the keys of the stored maps still considered."""
        if self._candidates is None:
            return [s.key for s in self._stored if s.key not in self.skipped]
        return [c.stored.key for c in self._candidates]

    def _rule(self, stored: StoredMap, params: Params, cells: LocalViewCells | CortexReader) -> EvidenceRule:
        """Return the evidence rule for ``stored``; a miss weighs as its matcher's observations say."""
        tolerance = self._tolerance(stored)
        evidence = params.merge_evidence_m if self._evidence_m is None else self._evidence_m
        probation = params.merge_probation_m if self._probation_m is None else self._probation_m
        return EvidenceRule.for_map(
            map_spacing(stored), tolerance, self._yaw_tolerance, evidence, probation,
            getattr(cells, "miss_weight", params.miss_weight), params.merge_probation_max_m,
        )

    def _tolerance(self, stored: StoredMap) -> float:
        """Return the position tolerance for ``stored``: as given, or :func:`default_position_tolerance`."""
        return default_position_tolerance(stored) if self._position_tolerance is None else self._position_tolerance

    def _prepare(self, engine: Engine) -> list[_Candidate]:
        candidates: list[_Candidate] = []
        for stored in self._stored:
            reason = params_incompatibility(stored.params, engine.params, reads_frames=True)
            if reason is None and engine.params.frontend == "sdr-htm" and self.absorbed:
                reason = "the session joined an sdr-htm map already (a session joins one sdr-htm map)"
            if reason:
                self.skipped[stored.key] = reason
                logger.info("map %r is not a merge candidate: %s", stored.key, reason)
                continue
            state = stored.state
            views = template_places(state) if engine.params.frontend == "sdr-htm" else None
            poses, templates, anchors = _predicting_places(state, views)
            order, starts = experiences_by_template(templates, int(np.shape(stored.snapshot.view.means)[0]))
            cells = self._matcher(engine, state, stored.key, self._tolerance(stored), views)
            rule = self._rule(stored, engine.params, cells)
            places = StoredPlaces(cells, poses, templates, engine.params.vt_match_threshold, engine.params.vt_panoramic,
                                  rule, loose=engine.params.frontend == "sdr-htm")  # fmt: skip
            candidates.append(_Candidate(stored, cells, order, starts, HypothesisSet(places, rule), anchors))
        self._track.keep_m = max((c.hypotheses.rule.history_m for c in candidates), default=0.0)
        if self._resume is not None:
            if self._readers and not self._restore_readers(self._resume):
                self._resume = MergerState(self._resume.odometry, self._resume.absorbed)  # readers restart
            self._resume.restore_into(candidates, self._track)
            self._resume = None
        return candidates

    def _restore_readers(self, state: MergerState) -> bool:
        """Continue the readers from a resumed state; False when its readers are not these (maps changed)."""
        if [int(cast(int, k)) for k, _ in state.readers] != [int(cast(int, r.key)) for r in self._readers]:
            return False
        widths = {np.shape(f[3])[-1] for f in state.track.frames} if state.track is not None else set()
        if widths - {self._readers[0].width}:  # views of another layout (stopped before lv_sdr existed)
            return False
        for reader, (_, arrays) in zip(self._readers, state.readers, strict=True):
            reader.load(arrays)
        return True

    def _matcher(
        self, engine: Engine, state: Mapping[str, np.ndarray], key: object, far_m: float,
        views: tuple[FloatArray, IntArray] | None = None,
    ) -> LocalViewCells | CortexReader:
        """Return the stored map's place matcher: its templates with the session's matcher, or its cortex's reader.

        ``far_m``: places further apart than this are different places to the reader's gate calibration;
        ``views``: the map's view-cell places (:func:`mapserver.merge.places.template_places`), when known.
        """
        if engine.params.frontend != "sdr-htm":
            cells = LocalViewCells.restore(engine.params, state)
            own = cast(LocalViewCells, engine.local_view)  # an lvc session's
            if own.column_rad > 0:  # the session's camera, for vt_shift_heading
                cells.column_rad = own.column_rad
            return cells
        from mapserver.merge.cortex import CortexReader  # torch only for sdr-htm sessions

        places = None if views is None else views[0]
        reader = CortexReader(engine.params, state, row=len(self._readers), key=key, far_m=far_m, places=places)
        self._readers.append(reader)
        return reader

    def _view(self, engine: Engine, result: StepResult, frame: SessionFrame | None) -> tuple[np.ndarray, float, object]:
        """Return the frame's view for the candidates, its mean, and what a probation keeps of it for the shadow.

        The view is the engine's template, or every reader's row; the probation keeps None (no readers), the rows,
        or an :class:`_Unread` frame. Where the ``sdr-htm`` maps all keep view-cell codes the readers' descriptors
        are not observations (the codes are, :meth:`CortexReader.match`), so the rows carry the frame's code alone
        and the readers read the frame later, in order: before a merge when a merge or a resume needs them
        (:meth:`_read_unread`), during a probation only if the merge is rolled back (:meth:`_remember_shadow`).
        """
        lv = engine.local_view
        if not self._readers or (not self._candidates and self.probation is None):
            assert lv.last_view is not None  # observe steps no frame without a view
            return lv.last_view, lv.last_mean, None
        if frame is None:
            msg = "sdr-htm merge candidates read the frames: call observe(engine, result, frame)"
            raise ValueError(msg)
        # readers are sdr-htm only: the frame's SDR, as the session's own cortex just encoded it
        code = cast("NeocortexViewCells", lv).last_code
        assert code is not None
        if all(r.codes is not None for r in self._readers):
            rows = np.stack([reader.code_row(code) for reader in self._readers])
            if self.probation is not None and not self._candidates:
                return rows, 0.0, _Unread(np.array(code))
            if not self.absorbed:  # read when a merge (or a resume) needs the readers: :meth:`_read_unread`
                self._unread.append((frame, _Unread(np.array(code)), result.template, result.template_created))
                self._unread_bytes += image_bytes(frame)
                if self._unread_bytes > LAZY_SHADOW_BYTES:
                    self._read_unread()
                return rows, 0.0, rows
        view = self._read(frame, code)
        if not self.absorbed:  # a view cell of the session's own cortex
            self._remember([(frame, view, result.template, result.template_created)])
        return view, 0.0, view

    def _read_unread(self) -> None:
        """Let the readers read the frames they have not read, in order, and keep the session's new view cells.

        Before a merge the observations are the view cells' codes, so the readers' descriptors serve only the merge
        (the session's view cells re-expressed in the map's cortex, :meth:`CortexReader.translated`) and a resume
        (their state): a session that never merges never reads, and one that merges reads each frame once, as
        reading alongside did. Called by :meth:`_merge`, :meth:`export_state`, and past ``LAZY_SHADOW_BYTES`` of
        held images.
        """
        self._remember(self._unread)
        self._unread.clear()
        self._unread_bytes = 0

    def _remember(self, frames: Sequence[tuple[SessionFrame, object, int, bool]]) -> None:
        """Keep the descriptors of the session's new view cells, frame by frame in order.

        Each entry is (frame, note, view cell, made there); the note is the readers' rows, or an :class:`_Unread`
        frame, which the readers read now (so that their sequence state is the one reading alongside gives).
        """
        for frame, note, template, created in frames:
            view = self._read(frame, note.code) if isinstance(note, _Unread) else cast("IntArray | None", note)  # rows
            if created and view is not None:
                for reader in self._readers:
                    reader.remember(template, view)

    def _read(self, frame: SessionFrame, code: UInt8Array) -> IntArray:
        """Step every reader's cortex on the frame (its SDR ``code``); return their rows, stacked."""
        sonar = getattr(frame, "sonar", None)
        return np.stack([reader.read(frame.image, sonar, code) for reader in self._readers])

    def _remember_shadow(self, probation: Probation) -> None:
        """During a probation the session's own cortex is the shadow's: keep its new view cells' descriptors.

        The shadow steps when it catches up (:meth:`Probation.catch_up`); each frame it stepped comes with what
        was noted when the frame was verified: the readers' rows, or (reads deferred) the frame's code, which the
        readers read now, in the frames' order, so that their sequence state is the one reading alongside gives.
        """
        self._remember(probation.stepped)
        probation.stepped.clear()

    def observe(
        self, engine: Engine, result: StepResult, frame: SessionFrame | None = None
    ) -> MergeEvent | Rollback | None:
        """Match the frame just processed against the candidates; merge, verify or roll back.

        Args:
            engine: the session's engine right after ``engine.step`` (partial or already merged).
            result: what that step returned (its motion feeds the driver's odometry).
            frame: the frame itself (``image``, ``motion``, ``stamp_ns``): needed while a merge is on
                probation, to step the session's engine without the merge.

        Returns:
            The merge made at this frame (continue in ``event.engine``), a :class:`Rollback`
            (continue in ``rollback.engine``), or None.
        """
        if self._candidates is None:
            self._candidates = self._prepare(engine)
        m = result.motion
        step = np.array([m.dx, m.dy, m.dz, m.dyaw])
        self._odometry = compose(self._odometry, step)
        if engine.local_view.last_view is None:
            return None
        view, mean, note = self._view(engine, result, frame)
        moved = float(np.linalg.norm(step[:3]))
        self._track.add(result.frame, self._odometry, moved, view, mean)
        if self.probation is not None:
            probation = self.probation
            verdict = self._verify(result, frame, note)
            self._remember_shadow(probation)
            if verdict is not None or self.probation is None or not probation.held_open(self._track.distance):
                return verdict
            return self._decide(engine, result, frame, view, mean, held=probation)
        return self._decide(engine, result, frame, view, mean)

    def _decide(
        self, engine: Engine, result: StepResult, frame: SessionFrame | None, view: np.ndarray, mean: float,
        held: Probation | None = None,
    ) -> MergeEvent | None:
        """Update every candidate's hypotheses with the frame and merge when one clearly wins.

        ``held``: a probation held open on a run of mismatches (:meth:`Probation.held_open`): the session has
        left that map's ground, so the other stored maps are weighed again, and a merge into one of them first
        passes the held probation (the session reached well-identified ground elsewhere; a probation cannot
        run beside another merge).
        """
        if not self._candidates:
            return None
        threshold = engine.params.vt_match_threshold
        for candidate in self._candidates:
            u, error, rel = candidate.cells.match(view, mean, limit=threshold)
            found = None
            if u >= 0 and error <= threshold:
                found = self._observation(candidate, engine, result.frame, u, error, rel)
                self.observed.add(candidate.stored.key)
            candidate.hypotheses.update(self._track, found, u if error <= threshold else -1)
        needed = self._confirm if self._confirm is not None else engine.params.merge_confirm
        decision = decide({c.stored.key: c.hypotheses for c in self._candidates}, needed)
        if decision is None:
            return None
        key, winner, rival = decision
        chosen = next(c for c in self._candidates if c.stored.key == key)
        if held is not None:
            held.reason = (
                f"held open on {held.miss_run_m:.2f} m of mismatches after its matches; the session went on to "
                f"merge into map {key!r}"
            )
            self._settle_probation(PASSED, result.frame)
        return self._merge(chosen, winner, rival, engine, result, frame)

    def _observation(
        self, candidate: _Candidate, engine: Engine, frame: int, u: int, error: float, rel: float
    ) -> Observation:
        """Return the frame's match of stored template u (its experience: the one a hypothesis expects)."""
        mine = candidate.order[candidate.starts[u] : candidate.starts[u + 1]]
        places = candidate.hypotheses.places
        place = -1
        if mine.size == 1:
            place = int(mine[0])
        elif mine.size > 1:
            predictions = [h.predict(self._odometry) for h in candidate.hypotheses.hypotheses]
            if not predictions:
                place = int(mine[0])
            else:
                gaps = [np.linalg.norm(places.poses[mine, :3] - p[:3], axis=1) for p in predictions]
                place = int(mine[int(np.argmin(np.min(gaps, axis=0)))])
        seen = np.zeros(4)
        experience = -1 if place < 0 else int(candidate.anchors[place])
        if place >= 0:
            seen = compose(places.poses[place], _heading(rel))
        return Observation(
            frame=frame, stored_template=u, stored_experience=experience, error=float(error), relative_rad=float(rel),
            partial_template=int(engine.local_view.current), odometry=self._odometry.copy(),
            packet=engine.pose_cells.best.copy(), seen=seen,
        )  # fmt: skip

    def _robot_pose(self, engine: Engine, odometry_then: FloatArray) -> FloatArray:
        """Return the robot's pose at an earlier frame (or frames, (N, 4)) in the session map's frame."""
        return compose(engine.map.robot_pose(), relative(self._odometry, odometry_then))

    def _ties(
        self, engine: Engine, winner: Hypothesis, candidate: _Candidate
    ) -> tuple[tuple[int, int, tuple[float, ...]], ...]:
        """Return the winner's hits as ties (:attr:`Match.ties`): a loop closure per view that put the robot in place.

        For each hit before the merge (history included), the session's experience nearest to where the robot
        was (its pose at that frame in the session map, :meth:`_robot_pose`) and the stored experience of the
        hit's place, at that experience's pose relative to it: the robot at the place the view put it.
        """
        places, anchors = candidate.hypotheses.places, candidate.anchors
        poses = engine.map.poses
        if not winner.hits or poses.shape[0] == 0 or places.poses.shape[0] == 0:
            return ()
        odometry = np.array([o for o, _ in winner.hits])
        seen = np.array([p for _, p in winner.hits])
        robots = self._robot_pose(engine, odometry)
        own = np.asarray(cKDTree(poses[:, :3]).query(robots[:, :3])[1])
        place = places.rows_at(seen)
        tie = compose(relative(poses[own], robots), relative(seen, places.poses[place]))
        ties = [(int(a), int(b), tuple(float(v) for v in t)) for a, b, t in zip(own, anchors[place], tie, strict=True)]
        return tuple(ties)

    def _merge(
        self, candidate: _Candidate, winner: Hypothesis, rival: float, engine: Engine, result: StepResult,
        frame: SessionFrame | None,
    ) -> MergeEvent:
        """Apply Algorithm 1 with the winning hypothesis's anchor and pairs; start its probation."""
        self._read_unread()
        self.observed.add(candidate.stored.key)
        anchor = winner.anchor
        pose = self._robot_pose(engine, anchor.odometry)
        if self._readers:  # the anchor may be a view cell's place: T must take the robot there, not onto its experience
            experience = candidate.hypotheses.places.poses[anchor.stored_experience]  # experiences come first
            pose = compose(pose, relative(anchor.seen, compose(experience, _heading(anchor.relative_rad))))
        match = Match(
            stored_template=anchor.stored_template, stored_experience=anchor.stored_experience,
            partial_template=anchor.partial_template, partial_pose=tuple(float(v) for v in pose),
            partial_packet=tuple(float(v) for v in anchor.packet), relative_rad=anchor.relative_rad,
            confirmations=len(winner.support), pairs=winner.pairs(),
            ties=self._ties(engine, winner, candidate) if TIE_HITS and not self._readers else (),
        )  # fmt: skip
        partial = engine.snapshot()
        reader = cast("CortexReader", candidate.cells) if self._readers else None
        merged, record = merge_engine(
            candidate.stored, engine, match, shift_lattice=self.shift_lattice,
            partial=partial if reader is None else reader.translated(partial),
            cortex=None if reader is None else reader.cortex(),
        )  # fmt: skip
        rule = candidate.hypotheses.rule
        evidence: dict[str, Any] = {
            "decision": {**winner.evidence(rule), "rival_score_m": round(rival, 3)},
            "rule": {"evidence_m": round(rule.evidence_m, 3), "probation_m": round(rule.probation_m, 3),
                     "reject_m": round(rule.reject_m, 3), "position_tolerance_m": round(rule.position_tolerance, 3),
                     "miss_weight": rule.miss_weight},
            "distance_m": round(self._track.distance, 3),
        }  # fmt: skip
        if reader is not None and reader.codes is not None:  # the code gate this map's observations passed
            evidence["rule"]["sdr_min_overlap"] = round(float(reader.min_overlap), 4)
        event = MergeEvent(
            key=candidate.stored.key, engine=merged, record=record, frame=result.frame,
            stamp=float(engine.last_stamp), absorbed=tuple(self.absorbed), match=match, partial=partial,
            odometry=self._odometry.copy(), evidence=evidence, session_pose=engine.map.robot_pose(),
        )  # fmt: skip
        logger.info(
            "merged into map %r at frame %d (%.2f m of evidence, rival %.2f m, %d templates, %d experiences)",
            candidate.stored.key, result.frame, winner.score(rule.miss_weight), rival, record.templates,
            record.experiences,
        )  # fmt: skip
        self.absorbed.append(candidate.stored.key)
        self.events.append(event)
        self._before_merge = list(self._candidates or [])
        self._candidates = [c for c in self._candidates or [] if c is not candidate]
        if self._readers:  # the merged map's cells are the first map's: no other cortex can read them
            for other in self._candidates:
                self.skipped[other.stored.key] = "the session joined sdr-htm map " f"{candidate.stored.key!r}" \
                    " (a session joins one sdr-htm map: another map's cortex cannot read the merged map's cells)"
            self._candidates = []
        for other in self._candidates:  # their pairs and packets refer to the engine before the merge
            other.hypotheses.hypotheses.clear()
        if rule.probation_m > 0:
            if frame is None:
                msg = "a merge on probation needs the frames: call observe(engine, result, frame)"
                raise ValueError(msg)
            n_loaded = int(np.shape(candidate.stored.snapshot.map.pose)[0])
            self.probation = Probation(
                candidate.stored.key, winner, candidate.hypotheses, engine, self._track.distance, n_loaded
            )
            self._probation_event = event
        return event

    def _verify(self, result: StepResult, frame: SessionFrame | None, note: object) -> Rollback | None:
        """Step the probation (``note``: what the shadow keeps of the frame, :meth:`_view`); pass or roll back."""
        probation = self.probation
        assert probation is not None
        if frame is None:
            msg = "a merge on probation needs the frames: call observe(engine, result, frame)"
            raise ValueError(msg)
        verdict = probation.step(self._track, result, frame, note)
        return None if verdict is None else self._settle_probation(verdict, result.frame)

    def _settle_probation(self, verdict: str, frame: int, status: str | None = None) -> Rollback | None:
        """Record the probation's verdict on its merge event; on REJECTED undo the merge (the shadow goes on).

        ``status``: the verification status recorded when the merge stays (default: the verdict).
        """
        probation, event = self.probation, self._probation_event
        assert probation is not None and event is not None
        event.evidence["verification"] = probation.evidence(self._track, status if verdict == PASSED and status
                                                            else verdict)  # fmt: skip
        self.probation = None
        if verdict == PASSED:
            logger.info("merge into map %r verified over %.2f m", event.key, self._track.distance - probation.start_m)
            return None
        assert verdict == REJECTED
        logger.warning("merge into map %r rolled back at frame %d: %s", event.key, frame, probation.reason)
        self.absorbed.pop()
        self.events.remove(event)
        self._candidates = self._before_merge
        for candidate in self._candidates:
            candidate.hypotheses.hypotheses.clear()
            self.skipped.pop(candidate.stored.key, None)
        probation.hset.ban(probation.hypothesis)
        shadow = probation.catch_up()
        self._remember_shadow(probation)
        rollback = Rollback(event, shadow, frame, tuple(probation.created), tuple(probation.seen))
        self.rollbacks.append(rollback)
        return rollback

    def finish(self) -> Rollback | None:
        """End a probation still running when the log ends: judge it on what it saw (``Probation.conclude_at_end``).

        A merge kept is recorded with verification status ``incomplete`` (its probation was cut short).
        Returns the :class:`Rollback` when that judgement rejects the merge: the caller continues (and stores)
        the session's engine without the merge, as after a rollback during the log.
        """
        if self.probation is None or self._probation_event is None:
            return None
        frame = int(self._track.last[0]) if self._track.frames else -1
        verdict = self.probation.conclude_at_end(self._track.distance)
        return self._settle_probation(verdict, frame, status="incomplete")  # kept: its verification cut short

    # ------------------------------------------------------------------ resume
    def export_state(self) -> MergerState:
        """Return what the driver carries to the next frame (see the module docstring, "Resume").

        Raises:
            RuntimeError: a probation is running (a session stops only after its probation concludes).
        """
        if self.probation is not None:
            msg = "a merge is on probation: run on until it concludes (or call finish()) before exporting the state"
            raise RuntimeError(msg)
        self._read_unread()
        hypotheses: dict[object, tuple[tuple[Hypothesis, ...], tuple[FloatArray, ...]]] = {}
        if self._candidates is not None:
            for c in self._candidates:
                hset = c.hypotheses
                if hset.hypotheses or hset.banned:
                    hypotheses[c.stored.key] = (tuple(hset.hypotheses), tuple(hset.banned))
        elif self._resume is not None:
            hypotheses = dict(self._resume.hypotheses)
        track = self._resume.track if self._candidates is None and self._resume is not None else self._track
        if self._candidates is None and self._resume is not None:
            readers = self._resume.readers
        else:
            readers = tuple((r.key, r.state()) for r in self._readers)
        return MergerState(self._odometry.copy(), tuple(self.absorbed), hypotheses, track, readers)


def _heading(rad: float) -> FloatArray:
    return np.array([0.0, 0.0, 0.0, rad])


def _predicting_places(
    state: Mapping[str, np.ndarray], views: tuple[FloatArray, IntArray] | None
) -> tuple[FloatArray, IntArray, IntArray]:
    """Return (poses (P, 4), templates (P,), anchor experiences (P,)) of the places a stored map predicts views at.

    The experiences; with ``views`` (sdr-htm maps: every view cell's own place and the experience it was made
    after, :func:`mapserver.merge.places.template_places`) also those places.
    """
    em = ExperienceMapSnapshot.from_arrays(state)
    poses = np.asarray(em.pose, dtype=np.float64).reshape(-1, 4)
    templates = np.asarray(em.template, dtype=np.int64).reshape(-1)
    anchors = np.arange(poses.shape[0], dtype=np.int64)
    if views is None:
        return poses, templates, anchors
    view_poses, view_anchor = views
    placed = np.flatnonzero(view_anchor >= 0)
    return (
        np.concatenate([poses, view_poses[placed]]),
        np.concatenate([templates, placed]),
        np.concatenate([anchors, view_anchor[placed]]),
    )

"""The online merge driver: fed after every frame of a session, it merges the session into stored maps.

Usage (what ``pipeline.py`` does)::

    merger = OnlineMerger([StoredMap(key, params, state), ...])
    engine = Engine(params, origin=tag)   # the session's origin tag (the store: its id, or 0 until it has one)
    for image, motion, stamp in frames:
        result = engine.step(image, motion, stamp)
        event = merger.observe(engine, result)
        if event is not None:          # store event.record; continue in the merged engine
            engine = event.engine

After every frame the current view (``engine.local_view.last_view``) is matched against
every candidate stored map's templates with the engine's own matcher
(``LocalViewCells.match`` with the match threshold as its limit, as the engine itself asks:
same thresholds, vectorised over templates, pairs that cannot match pruned). A merge needs the
confirmation of :mod:`mapserver.merge.confirm` (K consecutive agreeing frames, K from
``Params.merge_confirm`` unless given; K = 1 is the paper). Then the session's engine is
merged into that map (:func:`mapserver.merge.engines.merge_engine`), mapping continues in the
merged engine, and that map is no longer a candidate. The session may later merge again into
another stored map: the merged engine (session plus the first map) is then the partial map
and the second map the loaded one, so one session bridging two maps joins them into one.

Known start (Menezes et al. scenario i): a session that starts at a mapped place confirms
its match within its first K frames; every template and experience it has made by then
lies inside the confirmation window and is identified with the stored one, so the merge
leaves the stored map as it was, with the robot at the matched experience, and the session
maps on from there: no separate partial map remains.

Resume: :meth:`OnlineMerger.export_state` returns what the driver carries from frame to frame
(the session's odometry, the maps absorbed, the running confirmation streaks) as a
:class:`MergerState`; ``OnlineMerger(..., resume=state)`` continues from it, so a session
stopped after frame k and continued gives the merges of one run (the caller drops the streaks
of maps that changed in between: :meth:`MergerState.without`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from core import Engine, StepResult
from core.localview import LocalViewCells
from mapserver.merge.confirm import Observation, Streak
from mapserver.merge.engines import StoredMap, merge_engine
from mapserver.merge.record import Match, MergeRecord
from mapserver.merge.se3 import compose, relative
from mapserver.merge.snapshot import experiences_by_template, params_incompatibility

logger = logging.getLogger(__name__)

DEFAULT_YAW_TOLERANCE = 0.5
"""Radians between a match's heading and the heading the streak's odometry predicts."""


@dataclass(frozen=True, eq=False)
class MergeEvent:
    """One merge made by the online driver.

    Attributes:
        key: the stored map merged into (the loaded map).
        engine: the merged engine; the session continues in it.
        record: what the merge did (:class:`MergeRecord`).
        frame: the session frame that confirmed the merge.
        stamp: its log time (s).
        absorbed: keys of stored maps already merged into the session before this merge
            (they are part of the partial map here).
        match: the confirmed correspondence the merge applied (re-applying it to the same two
            states gives the same merged state: redo).
        partial: the session's engine snapshot right before the merge (the partial map; an
            undo restores it).
        odometry: (4,) the driver's odometry pose of the session at the frame (x, y, z, yaw).
    """

    key: object
    engine: Engine
    record: MergeRecord
    frame: int
    stamp: float
    absorbed: tuple[object, ...] = ()
    match: Match | None = None
    partial: Mapping[str, np.ndarray] | None = field(default=None, repr=False)
    odometry: np.ndarray | None = field(default=None, repr=False)


@dataclass(eq=False)
class _Candidate:
    stored: StoredMap
    cells: LocalViewCells
    order: np.ndarray
    starts: np.ndarray
    poses: np.ndarray
    streak: Streak
    matched_frames: int = field(default=0)


def default_position_tolerance(stored: StoredMap) -> float:
    """Return 3× the median odometry-link length of a stored map (its experience spacing), metres.

    A view matches a template over about one experience spacing, so agreeing matches may
    differ by that much; a map without links falls back to 2× the experience threshold in metres.
    """
    kind = np.asarray(stored.state["em_link_kind"])
    distance = np.asarray(stored.state["em_link_distance"], dtype=np.float64)[kind == 0]
    distance = distance[distance > 0]
    p = stored.params
    floor = 2.0 * p.exp_delta_pc_threshold * p.pc_cell_x_size
    if distance.size == 0:
        return floor
    return max(3.0 * float(np.median(distance)), 0.5 * floor)


class OnlineMerger:
    """Merges a running session into the stored maps it connects to.

    Args:
        stored: the candidate stored maps (maps whose parameters cannot merge with the
            session's are skipped, see :attr:`skipped`).
        confirm: K, consecutive agreeing frames needed; None → the session's ``Params.merge_confirm``.
        shift_lattice: False disables operation (iii) (debug, the paper's Fig. 12).
        position_tolerance: metres; None → :func:`default_position_tolerance` per map.
        yaw_tolerance: radians (default :data:`DEFAULT_YAW_TOLERANCE`).
        resume: the driver's state after an earlier part of the same session
            (:meth:`export_state`); streaks of maps not among ``stored`` are ignored.
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
    ) -> None:
        self._stored = list(stored)
        self._confirm = confirm
        self.shift_lattice = shift_lattice
        self._position_tolerance = position_tolerance
        self._yaw_tolerance = yaw_tolerance
        self._candidates: list[_Candidate] | None = None
        self.skipped: dict[object, str] = {}
        self.absorbed: list[object] = []
        self.events: list[MergeEvent] = []
        self._odometry = np.zeros(4)
        self._resume: MergerState | None = resume
        if resume is not None:
            self._odometry = np.asarray(resume.odometry, dtype=np.float64).copy()
            self.absorbed = list(resume.absorbed)

    @property
    def candidates(self) -> list[object]:
        """Return the keys of the stored maps still considered."""
        if self._candidates is None:
            return [s.key for s in self._stored if s.key not in self.skipped]
        return [c.stored.key for c in self._candidates]

    def _prepare(self, engine: Engine) -> list[_Candidate]:
        needed = self._confirm if self._confirm is not None else engine.params.merge_confirm
        candidates: list[_Candidate] = []
        for stored in self._stored:
            reason = params_incompatibility(stored.params, engine.params)
            if reason:
                self.skipped[stored.key] = reason
                logger.info("map %r is not a merge candidate: %s", stored.key, reason)
                continue
            state = stored.state
            templates = np.asarray(state["em_template"], dtype=np.int64)
            n_templates = int(np.shape(state["lv_means"])[0])
            order, starts = experiences_by_template(templates, n_templates)
            tolerance = self._position_tolerance
            if tolerance is None:
                tolerance = default_position_tolerance(stored)
            candidates.append(
                _Candidate(
                    stored=stored,
                    cells=LocalViewCells.restore(engine.params, state),  # the session's matcher
                    order=order,
                    starts=starts,
                    poses=np.asarray(state["em_pose"], dtype=np.float64).reshape(-1, 4),
                    streak=Streak(needed, tolerance, self._yaw_tolerance),
                )
            )
        if self._resume is not None:
            for candidate in candidates:
                entries, neutral, matched = self._resume.streaks.get(candidate.stored.key, ((), (), 0))
                candidate.streak.entries = list(entries)
                candidate.streak.neutral = list(neutral)
                candidate.matched_frames = matched
            self._resume = None
        return candidates

    def observe(self, engine: Engine, result: StepResult) -> MergeEvent | None:
        """Match the frame just processed against the candidates; merge when one is confirmed.

        Args:
            engine: the session's engine right after ``engine.step`` (partial or already merged).
            result: what that step returned (its motion feeds the confirmation's odometry).

        Returns:
            The merge made at this frame (continue in ``event.engine``), or None.
        """
        if self._candidates is None:
            self._candidates = self._prepare(engine)
        m = result.motion
        self._odometry = compose(self._odometry, np.array([m.dx, m.dy, m.dz, m.dyaw]))
        view = engine.local_view.last_view
        if view is None or not self._candidates:
            return None
        threshold = engine.params.vt_match_threshold
        confirmed: list[_Candidate] = []
        for candidate in self._candidates:
            u, error, relative = candidate.cells.match(view, engine.local_view.last_mean, limit=threshold)
            if u < 0 or error > threshold:
                candidate.streak.reset()
                continue
            candidate.matched_frames += 1
            observation = self._observation(candidate, engine, result.frame, u, error, relative)
            if candidate.streak.add(observation):
                confirmed.append(candidate)
        if not confirmed:
            return None
        chosen = max(confirmed, key=lambda c: (len(c.streak.entries), -c.streak.best.error))
        return self._merge(chosen, engine, result)

    def _observation(
        self, candidate: _Candidate, engine: Engine, frame: int, u: int, error: float, relative: float
    ) -> Observation:
        mine = candidate.order[candidate.starts[u] : candidate.starts[u + 1]]
        experience = -1
        if mine.size == 1:
            experience = int(mine[0])
        elif mine.size > 1:
            predicted = candidate.streak.predict(self._odometry)
            if predicted is None:
                experience = int(mine[0])
            else:
                gap = np.linalg.norm(candidate.poses[mine, :3] - predicted[:3], axis=1)
                experience = int(mine[int(np.argmin(gap))])
        seen = np.zeros(4)
        if experience >= 0:
            seen = compose(candidate.poses[experience], np.array([0.0, 0.0, 0.0, relative]))
        return Observation(
            frame=frame,
            stored_template=u,
            stored_experience=experience,
            error=float(error),
            relative_rad=float(relative),
            partial_template=int(engine.local_view.current),
            odometry=self._odometry.copy(),
            packet=engine.pose_cells.best.copy(),
            seen=seen,
        )

    def _robot_pose(self, engine: Engine, odometry_then: np.ndarray) -> np.ndarray:
        """Return the robot's pose at an earlier frame in the session map's frame (via odometry since)."""
        em = engine.map
        a = em.accum
        if em.current < 0:
            return np.array([0.0, 0.0, 0.0, a[3]])
        base = em.poses[em.current]
        now = np.array([base[0] + a[0], base[1] + a[1], base[2] + a[2], a[3]])
        return compose(now, relative(self._odometry, odometry_then))

    def _merge(self, candidate: _Candidate, engine: Engine, result: StepResult) -> MergeEvent:
        streak = candidate.streak
        anchor = streak.best
        pose = self._robot_pose(engine, anchor.odometry)
        match = Match(
            stored_template=anchor.stored_template,
            stored_experience=anchor.stored_experience,
            partial_template=anchor.partial_template,
            partial_pose=(float(pose[0]), float(pose[1]), float(pose[2]), float(pose[3])),
            partial_packet=tuple(float(v) for v in anchor.packet),
            relative_rad=anchor.relative_rad,
            confirmations=len(streak.entries),
            pairs=streak.pairs(),
        )
        partial = engine.snapshot()
        merged, record = merge_engine(
            candidate.stored, engine, match, shift_lattice=self.shift_lattice, partial=partial
        )
        event = MergeEvent(
            key=candidate.stored.key,
            engine=merged,
            record=record,
            frame=result.frame,
            stamp=float(engine.last_stamp),
            absorbed=tuple(self.absorbed),
            match=match,
            partial=partial,
            odometry=self._odometry.copy(),
        )
        logger.info(
            "merged into map %r at frame %d (%d confirmations, %d templates, %d experiences)",
            candidate.stored.key, result.frame, record.confirmations, record.templates, record.experiences,
        )
        self.absorbed.append(candidate.stored.key)
        self.events.append(event)
        self._candidates = [c for c in self._candidates or [] if c is not candidate]
        for other in self._candidates:  # their pairs and packets refer to the engine before the merge
            other.streak.reset()
        return event

    # ------------------------------------------------------------------ resume
    def export_state(self) -> MergerState:
        """Return what the driver carries to the next frame (see the module docstring, "Resume")."""
        streaks: dict[object, tuple[tuple[Observation, ...], tuple[Observation, ...], int]] = {}
        if self._candidates is not None:
            for c in self._candidates:
                if c.streak.entries or c.streak.neutral or c.matched_frames:
                    streaks[c.stored.key] = (tuple(c.streak.entries), tuple(c.streak.neutral), c.matched_frames)
        elif self._resume is not None:
            streaks = dict(self._resume.streaks)
        return MergerState(self._odometry.copy(), tuple(self.absorbed), streaks)


_FIXED_COLUMNS = 16  # key, kind, frame, template, experience, error, relative, partial template, odometry (4), seen (4)


@dataclass(frozen=True, eq=False)
class MergerState:
    """The online driver's state between two frames, for resuming a session later.

    Attributes:
        odometry: (4,) the session's odometry pose so far (x, y, z, yaw).
        absorbed: keys of the maps merged so far.
        streaks: stored-map key → (streak entries, neutral observations, frames that matched the map).
    """

    odometry: np.ndarray
    absorbed: tuple[object, ...] = ()
    streaks: Mapping[object, tuple[tuple[Observation, ...], tuple[Observation, ...], int]] = field(
        default_factory=dict
    )

    def without(self, keys: Sequence[object]) -> MergerState:
        """Return the state with the streaks of these maps dropped (maps that changed since)."""
        gone = set(keys)
        return MergerState(self.odometry, self.absorbed, {k: v for k, v in self.streaks.items() if k not in gone})

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Return the state as plain arrays (map keys must be integers).

        Keys: ``odometry``, ``absorbed``, ``matched``, ``streaks``.

        ``streaks`` has one float64 row per observation: key, kind (0 entry, 1 neutral), frame,
        stored template, stored experience, error, relative_rad, partial template, odometry (4),
        seen (4), packet (D); ``matched`` is (Q, 2) int64: key, frames that matched that map.
        """
        rows: list[np.ndarray] = []
        for key, (entries, neutral, _matched) in self.streaks.items():
            for kind, group in ((0, entries), (1, neutral)):
                for o in group:
                    head = [float(int(key)), float(kind), float(o.frame), float(o.stored_template),  # type: ignore[call-overload]
                            float(o.stored_experience), o.error, o.relative_rad, float(o.partial_template)]  # fmt: skip
                    rows.append(np.concatenate([head, o.odometry, o.seen, o.packet]).astype(np.float64))
        width = max((r.size for r in rows), default=_FIXED_COLUMNS)
        return {
            "odometry": np.asarray(self.odometry, dtype=np.float64).reshape(4).copy(),
            "absorbed": np.asarray([int(k) for k in self.absorbed], dtype=np.int64),  # type: ignore[call-overload]
            "matched": np.asarray(
                [[int(k), int(v[2])] for k, v in self.streaks.items()], dtype=np.int64  # type: ignore[call-overload]
            ).reshape(-1, 2),
            "streaks": np.vstack(rows) if rows else np.zeros((0, width), dtype=np.float64),
        }

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> MergerState:
        """Rebuild a state from :meth:`to_arrays` output."""
        table = np.asarray(arrays["streaks"], dtype=np.float64)
        matched = {int(k): int(v) for k, v in np.asarray(arrays["matched"], dtype=np.int64).reshape(-1, 2)}
        groups: dict[int, tuple[list[Observation], list[Observation]]] = {}
        for row in table:
            key = int(row[0])
            obs = Observation(
                frame=int(row[2]),
                stored_template=int(row[3]),
                stored_experience=int(row[4]),
                error=float(row[5]),
                relative_rad=float(row[6]),
                partial_template=int(row[7]),
                odometry=row[8:12].copy(),
                packet=row[_FIXED_COLUMNS:].copy(),
                seen=row[12:16].copy(),
            )
            groups.setdefault(key, ([], []))[int(row[1])].append(obs)
        keys = sorted(set(groups) | set(matched))
        streaks = {
            k: (tuple(groups.get(k, ([], []))[0]), tuple(groups.get(k, ([], []))[1]), matched.get(k, 0)) for k in keys
        }
        absorbed = tuple(int(k) for k in np.asarray(arrays["absorbed"], dtype=np.int64).reshape(-1))
        return cls(np.asarray(arrays["odometry"], dtype=np.float64).reshape(4).copy(), absorbed, streaks)

"""The SLAM engine: one object holding the whole state, advanced one camera frame at a time.

Per-frame order (OpenRatSLAM's node graph run in batch, as multisession-ratslam's
``Ratslam.__call__``; anchors §1.1 and §1.3):

1. motion: the log's odometry, or visual odometry from the image;
2. local view: match or create a template → (id, relative_rad);
3. pose cells ``on_view_template`` (link a new template / inject a known one);
4. pose cells ``on_odo``: excite, inhibit, global inhibition, normalise, path integration, decode;
5. experience decision ``get_action`` (create node / link to an existing experience / nothing),
   gated by VPR Guard and the motion gate when enabled (PoseidonSLAM);
6. experience map ``on_odo`` then the action;
7. a bounded share of graph relaxation (at most ``exp_loops`` iterations over at most
   ``exp_relax_batch`` experiences waiting for it; see :mod:`core.relaxation`).
   :meth:`Engine.settle` (end of a log) moves the map to the fixed point of full relaxation.

Everything is numpy and deterministic: the same frames give the same state, bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from enum import IntEnum
from typing import TYPE_CHECKING, cast

import numpy as np
import numpy.typing as npt

from core.arrays import FloatArray, IntArray, UInt8Array
from core.config import Departure
from core.experience_map import ExperienceMap, LinkKind
from core.gate import EventGate
from core.localview import LocalViewCells
from core.motion import ZERO_MOTION, Motion
from core.neuroslam.posecells import NeuroslamPoseCells
from core.paths import ExperienceGraph, NoPath, PathResult, Weight
from core.posecells import PoseCellNetwork
from core.snapshot import EngineSnapshot
from core.visual_odometry import VisualOdometry

if TYPE_CHECKING:
    from core.config import Params
    from core.mlif import MlifPoseCells
    from core.neocortex import NeocortexViewCells


def view_cells_class(params: Params) -> type[LocalViewCells] | type[NeocortexViewCells]:
    """Return the view module of ``params.frontend``: LVC templates, or SDR/HTM view cells (torch, lazy import)."""
    if params.frontend == "sdr-htm":
        from core.neocortex import NeocortexViewCells

        return NeocortexViewCells
    return LocalViewCells


def pose_cells_class(
    params: Params,
) -> type[PoseCellNetwork] | type[NeuroslamPoseCells] | type[MlifPoseCells]:
    """Return the pose cells of ``params.engine``: RatSLAM's lattice, or NeuroSLAM's grid and head-direction cells.

    ``pc_model = mlif`` (ratslam engine) gives the PC-MLIF spiking networks (torch, lazy import).
    """
    if params.engine == "neuroslam":
        return NeuroslamPoseCells
    if params.pc_model == "mlif":
        from core.mlif import MlifPoseCells

        return MlifPoseCells
    return PoseCellNetwork


class Action(IntEnum):
    """OpenRatSLAM ``TopologicalAction`` codes (0 = nothing)."""

    NONE = 0
    CREATE_NODE = 1
    CREATE_EDGE = 2
    SET_NODE = 3


@dataclass(frozen=True, slots=True)
class StepResult:
    """What one frame did."""

    frame: int
    template: int
    template_created: bool
    relative_rad: float
    action: Action
    experience: int
    loop_closure: bool
    motion: Motion


class Engine:
    """RatSLAM-family SLAM state machine (3-DoF RatSLAM or 4-DoF PoseidonSLAM lattice).

    Args:
        params: the parameter set (``core.config.Params``).
        origin: opaque tag stamped on templates and experiences created from now on
            (the store uses the session id); change it with :attr:`origin`.
        local_view: the view module to start from (:meth:`restore` passes the restored one); None builds an
            empty one of ``params.frontend``.
    """

    def __init__(
        self, params: Params, origin: int = 0, *, local_view: LocalViewCells | NeocortexViewCells | None = None
    ) -> None:
        self.params = params
        self.origin = origin
        self.local_view = view_cells_class(params)(params) if local_view is None else local_view
        self.odometry = VisualOdometry(params)
        self.pose_cells: PoseCellNetwork | NeuroslamPoseCells | MlifPoseCells = pose_cells_class(params)(params)
        self.map = ExperienceMap(params, self.pose_cells.rank)
        self.gate = EventGate(params)
        self.lv_origin: list[int] = []
        self.lv_place: list[int] = []
        """Per template: the experience current when it was made (−1: none yet)."""
        self.lv_place_offset: list[FloatArray] = []
        """Per template: the odometry accumulated since that experience then (x, y, z in the map frame, heading)."""
        self.lv_place_yaw: list[float] = []
        """Per template: that experience's heading then, so that its place turns as relaxation turns it."""
        self.frames = 0
        self.last_stamp = math.nan
        self.loop_closures = 0

    # ------------------------------------------------------------------ step
    def step(
        self, image: UInt8Array, motion: Motion | None, stamp: float, sonar: UInt8Array | None = None
    ) -> StepResult:
        """Process one camera frame with the motion since the previous one.

        Args:
            image: uint8 pixels (H, W) grey or (H, W, 3) RGB.
            motion: odometry since the previous frame, or None to use visual odometry.
            stamp: log time of the frame in seconds.
            sonar: the frame's sonar image, a second modality of the ``sdr-htm`` front-end (PoseidonSLAM
                Eq. 4.3); None: camera only.

        Raises:
            ValueError: a sonar image for the ``lvc`` front-end (intensity templates have one modality).

        Returns:
            The template, action and current experience after this frame.
        """
        if motion is None:
            dt = 0.0 if math.isnan(self.last_stamp) else max(stamp - self.last_stamp, 0.0)
            vtrans, vrot = self.odometry.process(image, dt)
            motion = Motion(vtrans * dt, 0.0, 0.0, vrot * dt, dt) if dt > 0 else ZERO_MOTION
        if sonar is None:
            template, relative_rad, created = self.local_view.process(image)
        elif self.params.frontend == "sdr-htm":
            template, relative_rad, created = cast("NeocortexViewCells", self.local_view).process(image, sonar)
        else:
            msg = "a sonar modality needs the sdr-htm front-end (--preset poseidon or neoslam)"
            raise ValueError(msg)
        if created:
            self.lv_origin.append(self.origin)
        self.pose_cells.on_view_template(template, relative_rad, self.local_view.count, created)
        self.pose_cells.on_odo(motion.dx, motion.dyaw, motion.dz)
        gate_open = self.gate.observe(template)
        action, target = self._get_action(template)
        self.map.on_odo(motion)
        loop_closure = False
        if action == Action.CREATE_NODE:
            a = self.map.accum
            if gate_open and self.gate.allows_event(a[0], a[1], a[2]):
                self.map.create_experience(template, self.pose_cells.best.copy(), stamp, self.origin)
            else:
                action = Action.NONE
        elif action == Action.CREATE_EDGE:
            # a link's facing takes the target's heading minus the robot's, a view's offset the opposite
            # (OpenRatSLAM passes its panoramic offset to both unchanged)
            shift_heading = self.params.vt_shift_heading and not self.params.openratslam_compat
            link_rad = -relative_rad if shift_heading else relative_rad
            if self._closure_faces_the_view(target):
                relative_rad = cast(LocalViewCells, self.local_view).view_heading(template)  # lvc only
                link_rad = -relative_rad
            loop_closure = self.map.create_link(self.map.current, target, link_rad, LinkKind.LOOP)
            self.map.set_experience(target, relative_rad)
            self.loop_closures += int(loop_closure)
        if created:
            self.lv_place.append(self.map.current)
            self.lv_place_offset.append(self.map.accum[:4].copy())
            current = self.map.current
            self.lv_place_yaw.append(float(self.map.poses[current, 3]) if current >= 0 else 0.0)
        if not self.params.follows_openratslam(Departure.RELAXATION):
            self.map.relax_step()
        elif action != Action.NONE:  # OpenRatSLAM relaxes after every published action
            self.map.iterate_openratslam()
        self.frames += 1
        self.last_stamp = stamp
        return StepResult(
            self.frames - 1, template, created, relative_rad, action, self.map.current, loop_closure, motion
        )

    def _closure_faces_the_view(self, target: int) -> bool:
        """Return whether a closure onto ``target`` takes the view's heading (``merge_view_heading``).

        A forward view's closure carries the robot's odometry facing whatever way the view is turned (OpenRatSLAM
        gives it no offset). A single session's map keeps that, as OpenRatSLAM makes it (``vt_shift_heading`` on
        every closure and view made the single routes of ``symmetric`` worse: docs/journal.md, "a merge that
        identified every partial experience makes a merged map", its probe of ``vt_shift_heading``). A merged map is
        settled on the joint least squares over positions and headings (``ExperienceMap.joint``), where a closure's
        heading error bends both sessions' chains; and a closure joining two sessions' experiences (``em_origin``)
        carries the robot's weave between their drives (docs/journal.md, "where two sessions meet, and in a merged
        map, a closure faces the way the view says": ``symmetric-overlap`` seed 5, two such links 24° apart). Those
        closures take the view's column shift against the matched template (:meth:`LocalViewCells.view_heading`),
        as ``vt_shift_heading`` gives every closure. Not for ``vt_shift_heading`` (every closure has it already),
        panoramic views (their match gives the offset), other front-ends, or ``openratslam_compat``.
        """
        p = self.params
        if not p.merge_view_heading or p.vt_shift_heading or p.vt_panoramic or p.openratslam_compat:
            return False
        if p.frontend != "lvc" or self.map.current < 0:
            return False
        origins = self.map.origins
        return bool(origins[self.map.current] != origins[target]) or self.map.joint

    def _get_action(self, template: int) -> tuple[Action, int]:
        """Choose the topological action (OpenRatSLAM ``PosecellNetwork::get_action``).

        Create an experience when the template has none; otherwise, when the packet
        moved more than ``exp_delta_pc_threshold`` cells from the current experience
        or the template changed, link to the closest other experience of this
        template if it is within the threshold (strictly), else create one. The
        distances are wrapped lattice distances with the heading corrected by the
        view's offset (``PoseCellNetwork.delta_to``). OpenRatSLAM's extra branch —
        "matched experience is the current one and the template is unchanged: create"
        — cannot fire there (the current experience is skipped in the search), so the
        no-match case covers it; SET_NODE never arises either.

        An experience that a merge moved into this lattice (``ExperienceMap.lattice_levers``) gets a wider
        gate: ``threshold + merge_lattice_slack · lever``, the lattice error that the merge's heading error
        makes at that lever arm (``mapserver.merge.states``, operation iii). Of the experiences within their
        gates the closest is linked, as OpenRatSLAM links the closest: every link OpenRatSLAM's gate makes is
        made the same, the slack only adds links where it would create an experience. With no merge every
        lever is 0 and the gate is OpenRatSLAM's.

        NeuroSLAM (``engine = neuroslam``; notes ``neuroslam.md`` §7.1) decides on its five codes with the same
        rule, plus its guard against false links: when more than one other experience of the template is within
        the threshold, nothing is done.
        """
        em = self.map
        candidates = em.experiences_of_template(template)
        if em.current < 0 or not candidates:
            return Action.CREATE_NODE, -1
        threshold = self.params.exp_delta_pc_threshold
        delta_current = float(self.pose_cells.delta_to(em.lattice_coords[em.current]))
        if delta_current <= threshold and template == self.pose_cells.prev_vt:
            return Action.NONE, -1
        others = [c for c in candidates if c != em.current]
        if others:
            deltas = self.pose_cells.delta_to(em.lattice_coords[others])
            within = deltas < threshold + self.params.merge_lattice_slack * em.lattice_levers[others]
            if self.params.engine == "neuroslam" and int(np.count_nonzero(within)) > 1:
                return Action.NONE, -1  # NeuroSLAM's guard: two candidates is a hash collision, not a place
            if within.any():
                return Action.CREATE_EDGE, others[int(np.argmin(np.where(within, deltas, np.inf)))]
        return Action.CREATE_NODE, -1

    # --------------------------------------------------------------- queries
    @property
    def template_count(self) -> int:
        """Return the number of local view templates."""
        return self.local_view.count

    @property
    def experience_count(self) -> int:
        """Return the number of experiences."""
        return self.map.count

    def graph(self) -> ExperienceGraph:
        """Return a path-query structure over the current experience graph."""
        src, dst, _, dt, distance, _ = self.map.links
        return ExperienceGraph(self.map.poses, src, dst, dt, distance)

    def shortest_path(self, source: int, target: int, weight: Weight = "time") -> PathResult | NoPath:
        """Return the shortest path between two experiences (see :class:`core.paths.ExperienceGraph`)."""
        return self.graph().shortest_path(source, target, weight)

    def settle(self, max_iterations: int = 100_000) -> int:
        """Move the map to the fixed point of full relaxation (see :meth:`ExperienceMap.settle`).

        Run it at the end of a log: afterwards every experience's relaxation
        correction is at most ``exp_relax_tolerance`` and the poses equal those that
        iterating full relaxation to convergence would give. Returns the number of
        checking iterations that were needed (normally 0).
        """
        return self.map.settle(max_iterations)

    # -------------------------------------------------------------- snapshot
    def snapshot(self) -> dict[str, np.ndarray]:
        """Return the whole state as plain arrays (schema in docs/architecture.md)."""
        state: dict[str, np.ndarray] = {}
        state.update(self.local_view.snapshot())
        state["lv_origin"] = np.asarray(self.lv_origin, dtype=np.int64)
        state["lv_place"] = np.asarray(self.lv_place, dtype=np.int64)
        state["lv_place_offset"] = np.asarray(self.lv_place_offset, dtype=np.float64).reshape(-1, 4)
        state["lv_place_yaw"] = np.asarray(self.lv_place_yaw, dtype=np.float64)
        state.update(self.odometry.snapshot())
        state.update(self.pose_cells.snapshot())
        state.update(self.map.snapshot())
        state.update(self.gate.snapshot())
        state["eng_frames"] = np.asarray(self.frames, dtype=np.int64)
        state["eng_last_stamp"] = np.asarray(self.last_stamp, dtype=np.float64)
        state["eng_loop_closures"] = np.asarray(self.loop_closures, dtype=np.int64)
        return state

    def typed_snapshot(self) -> EngineSnapshot:
        """Return :meth:`snapshot` as typed parts (:class:`core.snapshot.EngineSnapshot`)."""
        return EngineSnapshot.from_arrays(self.snapshot())

    @classmethod
    def restore(cls, params: Params, state: Mapping[str, np.ndarray], origin: int = 0) -> Engine:
        """Rebuild an engine from :meth:`snapshot` arrays so that it continues bit for bit."""
        engine = cls(params, origin, local_view=view_cells_class(params).restore(params, state))
        engine.lv_origin = np.asarray(state["lv_origin"], dtype=np.int64).tolist()
        place, offset = template_place_rows(state, len(engine.lv_origin))
        engine.lv_place, engine.lv_place_offset = place.tolist(), list(offset)
        engine.lv_place_yaw = template_place_yaws(state, len(engine.lv_origin)).tolist()
        engine.odometry = VisualOdometry.restore(params, state)
        engine.pose_cells = pose_cells_class(params).restore(params, state)
        engine.map = ExperienceMap.restore(params, engine.pose_cells.rank, state)
        engine.gate = EventGate.restore(params, state)
        engine.frames = int(state["eng_frames"])
        engine.last_stamp = float(state["eng_last_stamp"])
        engine.loop_closures = int(state.get("eng_loop_closures", np.asarray(0)))
        return engine


def template_rows(
    state: Mapping[str, np.ndarray], key: str, n: int, fill: float, dtype: npt.DTypeLike, width: int | None = None
) -> np.ndarray:
    """Return a snapshot's optional per-template array ``key`` as its first n rows ((n,) or (n, width)).

    Rows past the stored array's end, or all of them when the snapshot predates the key, are ``fill``.
    """
    shape = (n,) if width is None else (n, width)
    out = np.full(shape, fill, dtype=dtype)
    if key in state:
        stored = np.asarray(state[key], dtype=dtype).reshape((-1, *shape[1:]))[:n]
        out[: stored.shape[0]] = stored
    return out


def template_place_yaws(state: Mapping[str, np.ndarray], n: int) -> FloatArray:
    """Return (n,) the heading of each template's experience when the template was made (``lv_place_yaw``).

    NaN where unknown (templates past the key's end, or all of them in snapshots made before it): their
    offsets' headings are then taken as they were stored (absolute), not turned with the experience.
    """
    return template_rows(state, "lv_place_yaw", n, np.nan, np.float64)


def template_place_rows(state: Mapping[str, np.ndarray], n: int) -> tuple[IntArray, FloatArray]:
    """Return (place (n,), offset (n, 4)) of a snapshot's first n templates (``lv_place``/``lv_place_offset``).

    The keys are optional: templates past their end, or all of them in snapshots made before the keys
    existed, have no place (−1, zero offset).
    """
    place = template_rows(state, "lv_place", n, -1, np.int64)
    offset = template_rows(state, "lv_place_offset", n, 0.0, np.float64, width=4)
    return place, offset

"""Experience map: a semi-metric graph of SE(3) experiences with relaxation.

OpenRatSLAM's ``ExperienceMap`` (Ball et al. 2013; anchors §1.1; Menezes et al.
Eqs. 6–8) generalised to 4-DoF motion (x, y, z, yaw) as PoseidonSLAM's 3-D graph
(thesis Eqs. 4.20–4.21, with the clamps ``max_correction_norm`` and
``max_correction_step``). Poses are stored as (x, y, z, yaw); the quaternion is
the rotation ``yaw`` about z (roll and pitch are not represented).

A link holds the pose of its ``to`` experience in the frame of its ``from``
experience: translation (dx, dy, dz) and heading change dyaw — OpenRatSLAM's
``d``, ``heading_rad``, ``facing_rad`` written as a transform — plus Δt and the
Euclidean distance. Relaxation (its maths, fixed point, anchors and per-frame
budget) lives in :mod:`core.relaxation`.

Deliberate deviations from OpenRatSLAM:

* odometry arrives as the exact body-frame displacement of each frame
  (``Motion``), which is rotated by the accumulated facing before the facing
  advances; OpenRatSLAM integrates ``v·dt`` along the *new* facing;
* Δt of a link is the time since the current experience was set (OpenRatSLAM's
  ``accum_delta_time_s`` is never reset, so its links carry time since start);
* when relaxation turns the current experience, the odometry accumulated since
  it turns with it, so every link holds the odometry actually measured
  (OpenRatSLAM re-reads the experience's heading when the link is made, so a
  relaxation in between rotates the link);
* each connected part of the graph has an anchor, its lowest-id experience,
  that relaxation never moves (OpenRatSLAM lets the whole map drift; the
  relative geometry is the same). The first experience therefore stays where it
  was created: at the odometry accumulated before it (the origin when it is
  created on the first frame), facing ``exp_initial_em_deg``.

``openratslam_compat`` switches every one of these to OpenRatSLAM's code: ``v·dt``
along the new facing (sideways and vertical motion ignored), Δt since start, links
read the source's heading as it is then, and relaxation is OpenRatSLAM's
``iterate`` (:mod:`core.compat`: ``exp_loops`` sweeps after every action, nothing
anchored) instead of :meth:`ExperienceMap.relax_step` / :meth:`ExperienceMap.settle`.
``openratslam_parts`` does so part by part (``odometry``, ``link_dt``, ``relaxation``).

Defaults, chosen by ``bench/generalisation.py`` (forward-camera logs of four families × 20 seeds that no
default was tuned on; APE of the map against ground truth, as a ratio to OpenRatSLAM's code on the same frames,
median / 90th percentile over seeds 0–13, seeds 14–19 held out; ``park`` was never used to choose):

================  ==================  ==============  ==================  ==============
family            default (below)     held-out seeds  engine before       C++ core
================  ==================  ==============  ==================  ==============
street            0.70 / 1.12         0.17 / 0.93     0.75 / 1.15         1.00 / 1.00
campus            0.97 / 1.15         0.79 / 1.09     1.09 / 1.44         1.00 / 1.00
dusk              0.46 / 0.95         0.67 / 1.15     0.47 / 0.99         1.00 / 1.00
park (held out)   0.88 / 0.99         0.57 / 1.01     0.80 / 1.08         1.00 / 1.00
================  ==================  ==============  ==================  ==============

* our odometry, Δt and relaxation departures stay on: OpenRatSLAM's relaxation leaves the per-frame map where
  its sweeps reached and fails where aliased views close false loops (``street``, ``dusk``: compat's median APE
  1.0–1.2 m against 0.53–0.55 m); OpenRatSLAM's ``v·dt`` odometry (``openratslam_parts = odometry``) lost on
  ``campus`` (p90 1.18);
* ``exp_settle_joint`` (on): :meth:`settle` ends on the joint least squares over positions and headings, the
  loop and merge links weighed by ``exp_loop_weight`` (0.3) against an odometry link: a forward view's closure
  places the robot only within the closure gate and a few degrees round (measured on the bench's maps: true
  errors of loop links 0.2–0.3 m median, 1–2° median, up to 1 m and 6°, against 1–2 cm for a 0.5 m odometry
  link). RatSLAM's fixed point takes every closure as exact: ``campus`` 1.16 / 1.34 with the pose cells below;
  the weight swept: 1.0 → 0.99 / 1.23, 0.3 → 0.97 / 1.15, 0.2 → 0.96 / 1.17, 0.15 → 0.97 / 1.18;
* ``exp_robust_view`` (on, :meth:`core.robust.Drift.of`): the robust check counts the same view uncertainty in a
  loop link's ``z``; taken as precise as odometry, true closures of forward views were switched off (``campus``
  1.00 / 1.13 without the check, 0.99 / 1.23 with it, 0.97 / 1.15 with the view's uncertainty);
* settling helps on every family's median: APE before / after :meth:`settle`, median over the 20 seeds,
  ``street`` 0.77 / 0.55 m, ``campus`` 1.13 / 0.54, ``dusk`` 0.87 / 0.53, ``park`` 0.58 / 0.51. The
  per-frame map is what the budgeted relaxation reached; the settled one is the optimum of the links.

The panoramic and underwater presets (``circle``, ``poseidon``, ``neoslam``) keep RatSLAM's fixed point and
loop links as precise as odometry, as their merge benches measured them (``core.config``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from core import compat
from core._buffers import GrowBuffer
from core.angles import wrap_angle, wrap_angle_below_pi
from core.angles import wrap_angle_scalar as wrap_scalar
from core.arrays import BoolArray, FloatArray, Int8Array, Int32Array, IntArray
from core.config import Departure
from core.links import SWITCHABLE_KINDS
from core.links import LinkKind as LinkKind
from core.relaxation import (
    Incidence,
    PairSet,
    Worklist,
    length_weights,
    member_of,
    refine_jointly,
    residuals,
    roots,
    solve,
    solve_block,
    sorted_unique,
)
from core.robust import Drift, link_length, switch_off_outliers

if TYPE_CHECKING:
    from core.config import Params
    from core.motion import Motion


@dataclass(frozen=True, slots=True)
class _Standby:
    """Reckoning links on standby for one robust check (:meth:`ExperienceMap._standby`)."""

    src: IntArray  # (M,) the last experience created before a relocalisation
    dst: IntArray  # (M,) the experience created after it
    link: FloatArray  # (M, 6) dead reckoning between them: dx, dy, dz, dyaw (src frame), dt, distance
    partner: IntArray  # (M,) the odometry link each stands in for
    switchable: BoolArray  # (K,) odometry links made switchable by a reckoning link
    closure: IntArray  # (M,) the loop link from src made before the partner (the relocalisation's), or −1


class ExperienceMap:
    """Experiences, links, odometry accumulators and graph relaxation."""

    def __init__(self, params: Params, lattice_rank: int) -> None:
        self.params = params
        self.rank = lattice_rank
        self._pose = GrowBuffer((4,), np.float64)
        self._pc = GrowBuffer((lattice_rank,), np.float64)
        self._template = GrowBuffer((), np.int64)
        self._stamp = GrowBuffer((), np.float64)
        self._origin = GrowBuffer((), np.int64)
        self._lever = GrowBuffer((), np.float64)  # cells from the anchors of the merges that moved it (merge)
        self._from = GrowBuffer((), np.int64)
        self._to = GrowBuffer((), np.int64)
        self._transform = GrowBuffer((4,), np.float64)
        self._dt = GrowBuffer((), np.float64)
        self._distance = GrowBuffer((), np.float64)
        self._kind = GrowBuffer((), np.int8)
        self._active = GrowBuffer((), np.bool_)  # False: switched off by the robust check (core.robust)
        self._off = 0  # links switched off
        self._switchable = 0  # loop and merge links
        self._checked = 0  # loop and merge links at the last robust check
        self._stored = 0  # links that stood when the map was restored or last settled (STORED_LINK_HOLD)
        self._pairs = PairSet()  # every link's (source, target)
        self._exps_of_template: list[list[int]] = []
        self._incidence = Incidence()
        self._parent = GrowBuffer((), np.int64)  # union-find over links; a root is its component's anchor
        self._work = Worklist()
        self._operator: sp.csr_matrix | None = None
        self.current = -1
        self.previous = -1
        # dx, dy, dz (map frame), facing (rad), dt (s), distance (m) since the current experience
        self.accum = np.array([0.0, 0.0, 0.0, math.radians(params.exp_initial_em_deg), 0.0, 0.0])
        #: dead reckoning since the last experience created, in its frame: dx, dy, dz, dyaw, dt, distance
        self.reckon = np.zeros(6)
        self.last_created = -1
        self._reckon_from = GrowBuffer((), np.int64)  # reckoning links (docs/architecture.md): from, to, and
        self._reckon_to = GrowBuffer((), np.int64)  # the odometry between them (dx, dy, dz, dyaw, dt, distance)
        self._reckon_link = GrowBuffer((6,), np.float64)
        #: experience updates made by relaxation in the last :meth:`relax_step` (bounded per frame)
        self.last_relax_updates = 0

    # ------------------------------------------------------------- accessors
    @property
    def count(self) -> int:
        """Return the number of experiences."""
        return len(self._pose)

    @property
    def link_count(self) -> int:
        """Return the number of links."""
        return len(self._from)

    @property
    def poses(self) -> FloatArray:
        """Return experience poses (E, 4): x, y, z, yaw (view)."""
        return self._pose.view

    @property
    def lattice_coords(self) -> FloatArray:
        """Return experience lattice coordinates (E, D) (view)."""
        return self._pc.view

    @property
    def lattice_levers(self) -> FloatArray:
        """Return (E,) each experience's lattice lever arm: cells from the anchors of the merges that moved it.

        A merge moves a session's lattice coordinates by one rigid lattice transform about its anchor
        (``mapserver.merge.states``); its heading error misplaces a coordinate in proportion to this
        distance. 0 for an experience the map made itself.
        """
        return self._lever.view

    @property
    def templates(self) -> IntArray:
        """Return each experience's template id (E,) (view)."""
        return self._template.view

    @property
    def links(self) -> tuple[IntArray, IntArray, FloatArray, FloatArray, FloatArray, Int8Array]:
        """Return (from, to, transform (K,4), dt, distance, kind) views."""
        return (
            self._from.view,
            self._to.view,
            self._transform.view,
            self._dt.view,
            self._distance.view,
            self._kind.view,
        )

    @property
    def link_active(self) -> BoolArray:
        """Return each link's status (K,) bool: False when the robust check switched it off (view)."""
        return self._active.view

    @property
    def relax_pending(self) -> bool:
        """Return whether some experience's relaxation correction may still exceed ``exp_relax_tolerance``."""
        return len(self._work) > 0

    @relax_pending.setter
    def relax_pending(self, pending: bool) -> None:
        """Schedule every experience for relaxation (True) or drop the pending work (False)."""
        self._work.clear()
        if pending:
            self._work.push(np.flatnonzero(self._incidence.degree > 0))

    @property
    def relax_queue(self) -> IntArray:
        """Return the experiences waiting for relaxation, in order (a copy)."""
        return self._work.items()

    def anchors(self) -> BoolArray:
        """Return a boolean mask (E,) of the experiences relaxation never moves (one per connected part)."""
        return cast(BoolArray, roots(self._parent.view) == np.arange(self.count))

    def experiences_of_template(self, template: int) -> list[int]:
        """Return the experiences created with ``template`` (OpenRatSLAM ``PosecellVisualTemplate.exps``)."""
        if 0 <= template < len(self._exps_of_template):
            return self._exps_of_template[template]
        return []

    # --------------------------------------------------------------- updates
    def on_odo(self, motion: Motion) -> None:
        """Accumulate a frame's motion in the map frame (OpenRatSLAM ``ExperienceMap::on_odo``, 4-DoF).

        The body-frame displacement is rotated by the accumulated facing before the
        facing is advanced, so a frame's composed motion is applied exactly.
        """
        a = self.accum
        if self.params.follows_openratslam(Departure.ODOMETRY):  # turn first, then v·dt along the new facing
            robust = not self.params.follows_openratslam(Departure.RELAXATION)  # the robust check reads the reckoning
            for acc in (a, self.reckon) if robust else (a,):
                acc[3] = compat.clip_rad_180(acc[3] + motion.dyaw)
                acc[0] += motion.dx * math.cos(acc[3])
                acc[1] += motion.dx * math.sin(acc[3])
                acc[4] += motion.dt
                acc[5] += abs(motion.dx)
            return
        step = math.sqrt(motion.dx * motion.dx + motion.dy * motion.dy + motion.dz * motion.dz)
        for acc in (a, self.reckon):  # the map-frame accumulator, and the dead reckoning in the last new frame
            facing = acc[3]
            c, s = math.cos(facing), math.sin(facing)
            acc[0] += c * motion.dx - s * motion.dy
            acc[1] += s * motion.dx + c * motion.dy
            acc[2] += motion.dz
            acc[3] = wrap_scalar(facing + motion.dyaw)
            acc[4] += motion.dt
            acc[5] += step

    def robot_pose(self) -> FloatArray:
        """Return where the robot is now (4,): the current experience plus the odometry accumulated since.

        Menezes et al. Eq. 7's p_i + Δp_ij, facing the accumulated (absolute) heading; before the first
        experience, the odometry accumulated from the start. A new experience is created here.
        """
        pose = self.accum[:4].copy()
        if self.current >= 0:
            pose[:3] += self._pose.view[self.current, :3]
        return pose

    def create_experience(self, template: int, lattice: FloatArray, stamp: float, origin: int) -> int:
        """Create an experience at the current one plus the accumulated odometry; link and select it.

        Menezes et al. Eq. 7 / OpenRatSLAM2 Eq. 7: p_j = p_i + Δp_ij, facing the
        accumulated facing. The first experience sits at the odometry accumulated so
        far (the origin when it is created on the first frame) with the initial
        heading ``exp_initial_em_deg`` plus any turn since.
        """
        new_id = self._pose.append(self.robot_pose())
        self._pc.append(lattice)
        self._template.append(template)
        self._stamp.append(stamp)
        self._origin.append(origin)
        self._lever.append(0.0)
        self._incidence.add_nodes(1)
        self._parent.append(new_id)
        self._work.reserve(new_id + 1)
        self._operator = None
        while len(self._exps_of_template) <= template:
            self._exps_of_template.append([])
        self._exps_of_template[template].append(new_id)
        if self.current >= 0:
            self.create_link(self.current, new_id, 0.0, LinkKind.ODOMETRY)
        self._record_reckoning(new_id)
        self.set_experience(new_id, 0.0)
        return new_id

    def _record_reckoning(self, new_id: int) -> None:
        """Keep the dead reckoning from the last experience created to ``new_id`` when a relocalisation came between.

        The odometry link into ``new_id`` starts at the current experience, which a loop closure
        chose: if that closure was false, the link carries the false place on (a fold). The
        reckoning link is the robot's own odometry between the two experiences it created, which
        the robust check puts in that link's place when it switches the link off (:meth:`check_links`).
        """
        if self.params.follows_openratslam(Departure.RELAXATION):  # no robust check there: nothing to keep
            return
        if self.current >= 0 and self.last_created >= 0 and self.current != self.last_created:
            self._reckon_from.append(self.last_created)
            self._reckon_to.append(new_id)
            self._reckon_link.append(self.reckon.copy())
        self.last_created = new_id
        self.reckon[:] = 0.0

    def create_link(self, source: int, target: int, relative_rad: float, kind: LinkKind) -> bool:
        """Link ``source`` → ``target`` with the accumulated odometry; False if they are linked already.

        OpenRatSLAM ``on_create_link``: no link is added when one exists in either
        direction; the translation is expressed in the source's frame and the
        heading change includes the view's ``relative_rad``. Both ends of a link to
        anything but a brand-new experience (a loop closure) enter the relaxation
        worklist.
        """
        if source == target or (source, target) in self._pairs or (target, source) in self._pairs:
            return False
        a = self.accum
        yaw = self._pose.view[source, 3]
        c, s = math.cos(yaw), math.sin(yaw)
        transform = (c * a[0] + s * a[1], -s * a[0] + c * a[1], a[2], wrap_scalar(a[3] + relative_rad - yaw))
        self._append_link(source, target, transform, a[4], math.sqrt(a[0] ** 2 + a[1] ** 2 + a[2] ** 2), kind)
        if kind != LinkKind.ODOMETRY:
            self._work.push(np.array([source, target], dtype=np.int64))
        return True

    def add_link_raw(
        self,
        source: int,
        target: int,
        transform: FloatArray,
        dt: float,
        distance: float,
        kind: LinkKind,
        active: bool = True,
    ) -> bool:
        """Add a link with an explicit transform (merges, manual links); both ends enter the relaxation worklist.

        ``active`` False adds it switched off (a merge link made of a link its own map's robust check had
        switched off; the next check decides it afresh).
        """
        if (source, target) in self._pairs or source == target:
            return False
        self._append_link(source, target, np.asarray(transform, dtype=np.float64), dt, distance, int(kind))
        if not active:
            self._active.view[-1] = False
            self._off += 1
        self._work.push(np.array([source, target], dtype=np.int64))
        return True

    def _append_link(
        self, source: int, target: int, transform: tuple[float, ...] | FloatArray, dt: float, distance: float, kind: int
    ) -> None:
        link = self._from.append(source)
        self._to.append(target)
        self._transform.append(transform)
        self._dt.append(dt)
        self._distance.append(distance)
        self._kind.append(kind)
        self._active.append(True)
        self._switchable += int(kind in SWITCHABLE_KINDS)
        self._pairs.add(source, target)
        self._incidence.add_link(source, target, link)
        self._union(source, target)
        self._operator = None

    def _find(self, node: int) -> int:
        parent = self._parent.view
        while parent[node] != node:
            parent[node] = parent[parent[node]]
            node = int(parent[node])
        return node

    def _union(self, a: int, b: int) -> None:
        """Join the components of ``a`` and ``b``; the higher anchor stops being one and is scheduled."""
        ra, rb = self._find(a), self._find(b)
        if ra != rb:
            low, high = min(ra, rb), max(ra, rb)
            self._parent.view[high] = low
            self._work.push(np.array([high], dtype=np.int64))

    def set_experience(self, experience: int, relative_rad: float) -> None:
        """Make ``experience`` current and restart the accumulators (OpenRatSLAM ``on_set_experience``).

        Setting the experience that is already current changes nothing, as in OpenRatSLAM.
        """
        if experience == self.current:
            return
        self.previous = self.current
        self.current = experience
        elapsed = self.accum[4]
        self.accum[:] = 0.0
        if self.params.follows_openratslam(Departure.LINK_DT):  # OpenRatSLAM never resets accum_delta_time_s
            self.accum[4] = elapsed
        self.accum[3] = wrap_scalar(float(self._pose.view[experience, 3]) + relative_rad)

    def _turn_accumulator(self, turn: float) -> None:
        """Rotate the odometry accumulated since the current experience by ``turn`` (the experience turned)."""
        if turn == 0.0:
            return
        a = self.accum
        c, s = math.cos(turn), math.sin(turn)
        a[0], a[1] = c * a[0] - s * a[1], s * a[0] + c * a[1]
        a[3] = wrap_scalar(a[3] + turn)

    # ------------------------------------------------------------ relaxation
    def relax_step(self) -> int:
        """Run this frame's bounded share of relaxation; return the number of experiences updated.

        Takes at most ``exp_relax_batch`` experiences from the front of the worklist —
        widened, when fewer are waiting, by the experiences created just before and
        after each (trajectory neighbours) up to ``exp_relax_batch`` — and moves them
        towards the fixed point of relaxation with every other
        experience held where it is (:func:`core.relaxation.solve_block`: what
        iterating the relaxation over just those experiences converges to), by the
        fraction ``min(1, 2·exp_correction)`` of the way (0.5 — OpenRatSLAM's value,
        which fully corrects each link it visits — goes all the way), shortened
        uniformly so that no experience moves by more than ``max_correction_step`` or
        ``max_correction_norm`` in this frame. Experiences that move by more than
        ``exp_relax_tolerance`` put their neighbours outside the batch back on the
        worklist (and themselves, after a shortened step). The work is one dense
        solve of at most ``exp_relax_batch`` unknowns, whatever the map size.
        """
        p = self.params
        self.last_relax_updates = 0
        if p.exp_loops <= 0 or p.follows_openratslam(Departure.RELAXATION):
            return 0
        if p.exp_robust and self._switchable >= max(self._checked + 1, 2 * self._checked):
            self.check_links()
        if len(self._work) == 0:
            return 0
        ids = self._work.pop(p.exp_relax_batch)
        if ids.size < p.exp_relax_batch:  # widen the block along the trajectory: consecutive ids are neighbours
            reach = (p.exp_relax_batch // ids.size - 1) // 2
            if reach > 0:
                ids = sorted_unique((ids[:, None] + np.arange(-reach, reach + 1)[None, :]).ravel())
                ids = ids[(ids >= 0) & (ids < self.count)]
        ids = ids[(self._incidence.degree[ids] > 0) & (self._parent.view[ids] != ids)]  # anchors never move
        if ids.size == 0:
            return 0
        links, owner = self._incidence.gather(ids)
        if self._off:
            ids, links, owner = self._active_links_of(ids, links, owner)
            if ids.size == 0:
                return 0
        src = self._from.view[links]
        dst = self._to.view[links]
        pose = self._pose.view
        target, winding_changed = solve_block(pose, ids, owner, src, dst, self._transform.view[links])
        step = target - pose[ids]
        step[:, 3] = wrap_angle_below_pi(step[:, 3])
        fraction = min(1.0, 2.0 * p.exp_correction)
        largest = float(np.sqrt(np.einsum("ij,ij->i", step[:, :3], step[:, :3])).max()) * fraction
        for cap in (p.max_correction_step, p.max_correction_norm):
            if cap > 0 and largest > cap:
                fraction *= cap / largest
                largest = cap
        step *= fraction
        moved = np.abs(step).max(axis=1) > p.exp_relax_tolerance
        self.last_relax_updates = int(ids.size)
        if not moved.any():
            return self.last_relax_updates
        pose[ids[moved]] += step[moved]
        pose[ids[moved], 3] = wrap_angle(pose[ids[moved], 3])
        where_current = np.flatnonzero(ids[moved] == self.current)
        if where_current.size:
            self._turn_accumulator(float(step[moved][where_current[0], 3]))
        is_source = src == ids[owner]
        neighbours = np.where(is_source, dst, src)[moved[owner]]
        if fraction < 1.0 or winding_changed:
            self._work.push(np.concatenate([ids[moved], neighbours]))
        else:  # the batch sits at its own fixed point: only the neighbours outside it may have to follow
            self._work.push(neighbours[~member_of(neighbours, np.sort(ids))])
        return self.last_relax_updates

    def _relaxation_operator(self) -> sp.csr_matrix:
        """Return the (E, K) sparse map from link residuals to corrections, c/degree, anchors' rows zero.

        Switched-off links have zero columns and do not count in the degree.
        """
        if self._operator is None:
            n = self.count
            k = self.link_count
            rows = np.concatenate([self._from.view, self._to.view])
            cols = np.concatenate([np.arange(k), np.arange(k)])
            on = np.concatenate([self._active.view, self._active.view])
            degree = np.bincount(rows[on] if self._off else rows, minlength=n).astype(np.float64)
            degree[degree == 0] = 1.0
            free = ~self.anchors()
            vals = np.concatenate([np.ones(k), -np.ones(k)]) * (self.params.exp_correction / degree[rows]) * free[rows]
            if self._off:
                vals = vals * on
            self._operator = sp.csr_matrix((vals, (rows, cols)), shape=(n, k))
        return self._operator

    def _active_links_of(
        self, ids: IntArray, links: Int32Array, owner: IntArray
    ) -> tuple[IntArray, Int32Array, IntArray]:
        """Drop switched-off links from a gathered block, and the block members left without a link."""
        keep = self._active.view[links]
        links, owner = links[keep], owner[keep]
        counts = np.bincount(owner, minlength=ids.size)
        if np.all(counts > 0):
            return ids, links, owner
        remap = np.cumsum(counts > 0) - 1
        return ids[counts > 0], links, remap[owner]

    def check_links(self) -> bool:
        """Run the robust check (:func:`core.robust.switch_off_outliers`); return whether a link changed status.

        Loop and merge links inconsistent with the rest of the graph are switched off,
        and switched-off links that became consistent are switched back on; when any
        changes, the map moves to the fixed point of relaxation over the active links.
        An odometry link that leaves an experience a loop closure chose, towards a new one, is
        switchable too, with its reckoning link on standby (:meth:`_record_reckoning`): when the
        check switches that odometry link off, the reckoning link joins the map as an odometry
        link, so a false relocalisation's fold is undone, not only its closure. An odometry link that a
        check switched off stays switchable whether or not its reckoning link is still held (the check
        turns every link it may not switch on).
        """
        checked, self._checked = self._checked, self._switchable
        if self._switchable == 0:
            return False
        drift = self._drift()
        src, dst, transform, _, distance, kind = self.links
        standby = self._standby(src, dst, kind)
        previous = self._active.view.copy()  # the status quo: the switches as they stand, new links off
        previous[np.flatnonzero(np.isin(kind, SWITCHABLE_KINDS))[checked:]] = False
        k = src.size
        odometry = np.zeros(standby.src.size, np.int8)
        result = switch_off_outliers(
            self._pose.view, np.concatenate([src, standby.src]), np.concatenate([dst, standby.dst]),
            np.concatenate([transform, standby.link[:, :4]]), np.concatenate([kind, odometry]),
            np.concatenate([distance, standby.link[:, 5]]), self.anchors(), drift, standby=standby.partner,
            also_switchable=standby.switchable | ~self._active.view, standby_closure=standby.closure, joint=self.joint,
            previous=previous, standing=self._active.view, stored=np.arange(k) < self._stored,
        )  # fmt: skip
        joined = np.flatnonzero(result.active[k:])
        if np.array_equal(result.active[:k], self._active.view) and joined.size == 0:
            return False
        self._active.view[:] = result.active[:k]
        self._off = int(np.count_nonzero(~result.active[:k]))
        for j in joined.tolist():  # the robot's own odometry replaces a fold
            row = standby.link[j]
            self._append_link(int(standby.src[j]), int(standby.dst[j]), row[:4].copy(), float(row[4]), float(row[5]),
                              int(LinkKind.ODOMETRY))  # fmt: skip
        self._operator = None
        self._adopt(result.pose)
        return True

    def _adopt(self, pose: FloatArray) -> None:
        """Move every experience to ``pose`` (the check's fixed point over the active links; turns the accumulator).

        The check solved with the heading windings dead-reckoned along the odometry
        (:func:`core.robust.chain_headings`); re-solving from the current headings instead would take
        a fold's windings (headings off by about π round to either winding).
        """
        current = self._pose.view
        start_yaw = float(current[self.current, 3]) if self.current >= 0 else 0.0
        current[:] = pose
        current[:, 3] = wrap_angle(current[:, 3])
        if self.current >= 0:
            self._turn_accumulator(wrap_scalar(float(current[self.current, 3]) - start_yaw))
        self._work.clear()

    def _standby(self, src: IntArray, dst: IntArray, kind: Int8Array) -> _Standby:
        """Return the reckoning links not yet in the map, and which odometry links they stand in for.

        Each reckoning link (a → n) pairs with the odometry link into ``n`` from the experience a
        loop closure chose (c → n, c ≠ a): that link becomes switchable (``switchable``, a (K,)
        mask), and the reckoning link, unless the map already holds it, is returned with
        ``partner`` = c → n's index: the check turns it on exactly when c → n is off.
        """
        k, n = src.size, self.count
        a, to = self._reckon_from.view, self._reckon_to.view
        odometry = np.flatnonzero(kind == int(LinkKind.ODOMETRY))[::-1]
        into = np.full(n, -1, dtype=np.int64)
        into[dst[odometry]] = odometry  # the first odometry link into each experience: the one that made it
        partner = into[to] if to.size else np.zeros(0, np.int64)
        valid = (partner >= 0) & (src[np.maximum(partner, 0)] != a)
        switchable = np.zeros(k, dtype=bool)
        switchable[partner[valid]] = True
        joined = np.flatnonzero((kind == int(LinkKind.ODOMETRY)) | (kind == int(LinkKind.MERGE)))
        ends = np.sort(np.stack([src[joined], dst[joined]], axis=1), axis=1) @ np.array([1, n], dtype=np.int64)
        # joined the map as an odometry link (or as a merge link, where a merge identified an end)
        held = np.isin(np.minimum(a, to) + n * np.maximum(a, to), ends)
        pick = valid & ~held
        closure = _last_loop_from(src, kind, a[pick], partner[pick])
        return _Standby(a[pick], to[pick], self._reckon_link.view[pick], partner[pick], switchable, closure)

    def _solve_active(self) -> None:
        """Move every experience to the fixed point of relaxation over the active links (turning the accumulator)."""
        pose = self._pose.view
        start_yaw = float(pose[self.current, 3]) if self.current >= 0 else 0.0
        on = self._active.view
        src, dst, transform = self._from.view, self._to.view, self._transform.view
        if self._off:
            src, dst, transform = src[on], dst[on], transform[on]
        pose[:] = solve(pose, src, dst, transform, self.anchors())
        if self.current >= 0:
            self._turn_accumulator(wrap_scalar(float(pose[self.current, 3]) - start_yaw))
        self._work.clear()

    def full_corrections(self) -> FloatArray:
        """Return every experience's relaxation correction (E, 4) under the current poses (no clamps)."""
        src, dst, transform = self._from.view, self._to.view, self._transform.view
        return self._relaxation_operator() @ residuals(self._pose.view, src, dst, transform)

    def relax(self, iterations: int | None = None) -> int:
        """Relax the whole graph: full simultaneous iterations over every link; return the number run.

        Each iteration moves every experience by its correction (Menezes et al.
        Eq. 8 with the corrected incoming-link sign of thesis Eq. 4.21, in 3-D plus
        heading; see :mod:`core.relaxation`), anchors excepted. ``max_correction_step``
        caps each experience's translation per iteration and ``max_correction_norm``
        its total translation in this call (thesis §4.2.4). Runs ``iterations``
        (default ``exp_loops``) iterations, stopping early once the largest
        correction is at most ``exp_relax_tolerance``; the worklist is then emptied,
        otherwise every linked experience is put on it.
        """
        p = self.params
        loops = p.exp_loops if iterations is None else iterations
        if self.link_count == 0 or loops <= 0:
            return 0
        operator = self._relaxation_operator()
        src, dst, transform = self._from.view, self._to.view, self._transform.view
        pose = self._pose.view
        total = np.zeros((self.count, 3)) if p.max_correction_norm > 0 else None
        start_yaw = float(pose[self.current, 3]) if self.current >= 0 else 0.0
        run = 0
        converged = False
        for _ in range(loops):
            run += 1
            correction = operator @ residuals(pose, src, dst, transform)
            _clamp(correction, p.max_correction_step, p.max_correction_norm, total)
            if float(np.abs(correction).max()) <= p.exp_relax_tolerance:
                converged = True
                break
            pose += correction
        pose[:, 3] = wrap_angle(pose[:, 3])
        if self.current >= 0:
            self._turn_accumulator(wrap_scalar(float(pose[self.current, 3]) - start_yaw))
        self.relax_pending = not converged
        return run

    def settle(self, max_iterations: int = 100_000) -> int:
        """Move every experience to the fixed point of full relaxation; return the check iterations run.

        The fixed point is computed directly (:func:`core.relaxation.solve`: one
        sparse factorisation of the link graph), which equals iterating :meth:`relax`
        until it converges — ignoring the clamps, which only limit how fast the map
        moves, not where it settles. Then the corrections are checked once; should
        any still exceed ``exp_relax_tolerance`` (a heading winding that changed),
        :meth:`relax` runs until they do not, at most ``max_iterations`` iterations.
        ``exp_loops = 0`` switches relaxation off: nothing moves. With ``exp_robust``
        the robust check (:meth:`check_links`) runs first, and the fixed point is that
        of the active links. With :attr:`joint` (ours: ``exp_relax_joint``, off by default, or a merged map
        with ``merge_relax_joint``) the map then moves on to the joint least squares over positions and
        headings (:func:`core.relaxation.refine_jointly`).
        """
        self._work.clear()
        if self.link_count == 0 or self.params.exp_loops <= 0 or self.params.follows_openratslam(Departure.RELAXATION):
            return 0
        if not (self.params.exp_robust and self.check_links()):
            self._solve_active()
        run = 0
        while run < max_iterations and float(np.abs(self.full_corrections()).max()) > self.params.exp_relax_tolerance:
            run += self.relax(min(1000, max_iterations - run))
        if self.joint or self.params.exp_settle_joint:
            self._refine_jointly()
        self._work.clear()
        self._stored = self.link_count  # a settled map is a finished one: its links stand as stored
        return run

    @property
    def origins(self) -> IntArray:
        """Return each experience's origin tag (the session that created it; a view, not a copy)."""
        return self._origin.view

    @property
    def joint(self) -> bool:
        """Return whether the settled map and the robust check use the joint least squares (not RatSLAM's fixed point).

        ``exp_relax_joint`` for every map; ``merge_relax_joint`` for a merged map: one that holds a merge link
        or experiences of more than one session (``em_origin``; a merge that identified every experience of the
        partial map leaves no merge link; docs/journal.md, "a merge that identified every partial experience makes a
        merged map": ``symmetric-overlap`` seed 15, 0.99 → 0.52 m). A
        merged map's closures carry the merge's heading error, which RatSLAM's fixed point (headings relaxed apart
        from the position residuals) turns into a misclosure in position; a true merge or closure then looks like
        an outlier to the robust check (docs/journal.md, "three tries at the heading errors of forward-view
        closures": ``twin-overlap`` 40 m seed 7). A single session's
        map is relaxed as OpenRatSLAM relaxes it.
        """
        p = self.params
        if p.exp_relax_joint:
            return True
        if not p.merge_relax_joint:
            return False
        origin = self._origin.view
        return bool(np.any(self._kind.view == int(LinkKind.MERGE))) or bool(np.any(origin != origin[:1]))

    def _drift(self) -> Drift:
        """Return the expected odometry drift that normalises link residuals (``exp_robust_*``)."""
        return Drift.of(self.params)

    def _refine_jointly(self) -> None:
        """Move the settled map to the joint least squares over its active links (``exp_relax_joint``)."""
        active = np.flatnonzero(self._active.view)
        weight = length_weights(self._distance.view[active], link_length(self._distance.view, self._kind.view))
        view_links = np.isin(self._kind.view[active], (int(LinkKind.LOOP), int(LinkKind.MERGE)))
        weight[view_links] *= self.params.exp_loop_weight
        self._pose.view[:] = refine_jointly(
            self._pose.view, self._from.view[active], self._to.view[active], self._transform.view[active],
            self.anchors(), heading_weight=self._drift().heading_weight, iterations=5, weight=weight,
        )  # fmt: skip

    def iterate_openratslam(self) -> None:
        """Relax as OpenRatSLAM's ``ExperienceMap::iterate`` (``exp_loops`` sweeps; see :mod:`core.compat`)."""
        p = self.params
        compat.iterate(
            self._pose.view, self._from.view, self._to.view, self._transform.view, p.exp_loops, p.exp_correction
        )
        self._work.clear()

    # -------------------------------------------------------------- snapshot
    def snapshot(self) -> dict[str, np.ndarray]:
        """Return the map as plain arrays (keys ``em_*`` of docs/architecture.md)."""
        return {
            "em_pose": self._pose.copy(),
            "em_pc": self._pc.copy(),
            "em_template": self._template.copy(),
            "em_stamp": self._stamp.copy(),
            "em_origin": self._origin.copy(),
            "em_pc_lever": self._lever.copy(),
            "em_link_from": self._from.copy(),
            "em_link_to": self._to.copy(),
            "em_link_transform": self._transform.copy(),
            "em_link_dt": self._dt.copy(),
            "em_link_distance": self._distance.copy(),
            "em_link_kind": self._kind.copy(),
            "em_link_active": self._active.copy(),
            "em_robust_checked": np.asarray(self._checked, dtype=np.int64),
            "em_stored_links": np.asarray(self._stored, dtype=np.int64),
            "em_current": np.asarray(self.current, dtype=np.int64),
            "em_previous": np.asarray(self.previous, dtype=np.int64),
            "em_accum": self.accum.copy(),
            "em_relax_pending": np.asarray(self.relax_pending, dtype=bool),
            "em_relax_queue": self._work.items(),
            "em_reckon_from": self._reckon_from.copy(),
            "em_reckon_to": self._reckon_to.copy(),
            "em_reckon_link": self._reckon_link.copy(),
            "em_reckon": self.reckon.copy(),
            "em_last_created": np.asarray(self.last_created, dtype=np.int64),
        }

    @classmethod
    def restore(cls, params: Params, lattice_rank: int, state: Mapping[str, np.ndarray]) -> ExperienceMap:
        """Rebuild a map from :meth:`snapshot` arrays, exactly.

        ``em_pc_lever`` (default: 0, no merge moved it), ``em_link_active`` (default: every link on),
        ``em_robust_checked`` (default: checked with every link there is) and the reckoning keys (default:
        none kept, no experience created since) are optional. ``em_relax_queue`` is optional: without it a
        pending relaxation (``em_relax_pending``) schedules every linked experience.
        """
        em = cls(params, lattice_rank)
        em._pose = GrowBuffer.from_array(np.asarray(state["em_pose"]).reshape(-1, 4), np.float64)
        em._pc = GrowBuffer.from_array(np.asarray(state["em_pc"]).reshape(-1, lattice_rank), np.float64)
        em._template = GrowBuffer.from_array(state["em_template"], np.int64)
        em._stamp = GrowBuffer.from_array(state["em_stamp"], np.float64)
        em._origin = GrowBuffer.from_array(state["em_origin"], np.int64)
        em._lever = GrowBuffer.from_array(per_experience_array(state, "em_pc_lever", len(em._origin.view)), np.float64)
        em._from = GrowBuffer.from_array(state["em_link_from"], np.int64)
        em._to = GrowBuffer.from_array(state["em_link_to"], np.int64)
        em._transform = GrowBuffer.from_array(np.asarray(state["em_link_transform"]).reshape(-1, 4), np.float64)
        em._dt = GrowBuffer.from_array(state["em_link_dt"], np.float64)
        em._distance = GrowBuffer.from_array(state["em_link_distance"], np.float64)
        em._kind = GrowBuffer.from_array(state["em_link_kind"], np.int8)
        active = np.ones(len(em._kind), dtype=bool)  # links a state lists no status for are on
        given = np.asarray(state.get("em_link_active", np.zeros(0, dtype=bool)), dtype=bool).reshape(-1)
        active[: min(given.size, active.size)] = given[: active.size]
        em._active = GrowBuffer.from_array(active, np.bool_)
        em._off = int(np.count_nonzero(~active))
        em._switchable = int(np.count_nonzero(np.isin(em._kind.view, SWITCHABLE_KINDS)))
        em._checked = int(state.get("em_robust_checked", np.asarray(em._switchable)))
        em._stored = int(state.get("em_stored_links", np.asarray(len(em._kind))))
        src, dst = em._from.view, em._to.view
        em._pairs = PairSet(src, dst)
        n = em.count
        em._incidence = Incidence.from_links(n, src, dst)
        em._parent = GrowBuffer.from_array(_component_minimum(n, src, dst), np.int64)
        em._work.reserve(n)
        templates = em._template.view
        n_templates = int(templates.max()) + 1 if templates.size else 0
        em._exps_of_template = [[] for _ in range(n_templates)]
        for exp_id, template in enumerate(templates.tolist()):
            em._exps_of_template[template].append(exp_id)
        em.current = int(state["em_current"])
        em.previous = int(state["em_previous"])
        em.accum = np.asarray(state["em_accum"], dtype=np.float64).copy()
        em._reckon_from = GrowBuffer.from_array(state.get("em_reckon_from", np.zeros(0, np.int64)), np.int64)
        em._reckon_to = GrowBuffer.from_array(state.get("em_reckon_to", np.zeros(0, np.int64)), np.int64)
        reckoned = np.asarray(state.get("em_reckon_link", np.zeros((0, 6))), dtype=np.float64).reshape(-1, 6)
        em._reckon_link = GrowBuffer.from_array(reckoned, np.float64)
        em.reckon = np.asarray(state.get("em_reckon", np.zeros(6)), dtype=np.float64).copy()
        em.last_created = int(state.get("em_last_created", np.asarray(-1)))
        if "em_relax_queue" in state:
            em._work.extend_ordered(np.asarray(state["em_relax_queue"], dtype=np.int64))
        elif bool(state["em_relax_pending"]):
            em.relax_pending = True
        return em


def per_experience_array(state: Mapping[str, object], key: str, n: int) -> FloatArray:
    """Return the optional per-experience float array ``key`` of a snapshot fitted to ``n`` experiences.

    Experiences past the end of the stored array (or all, when the state lacks it) get 0; entries past the
    ``n``-th are dropped. Used for ``em_pc_lever`` by the map, the merge and the store alike.
    """
    out = np.zeros(n, dtype=np.float64)
    given = np.asarray(state.get(key, np.zeros(0)), dtype=np.float64).reshape(-1)[:n]
    out[: given.size] = given
    return out


def _clamp(correction: FloatArray, step_cap: float, norm_cap: float, total: FloatArray | None) -> None:
    """Apply the thesis clamps in place: per-iteration translation ≤ ``step_cap``, running total ≤ ``norm_cap``."""
    if step_cap > 0:
        norms = np.sqrt(np.einsum("ij,ij->i", correction[:, :3], correction[:, :3]))
        over = norms > step_cap
        if over.any():
            correction[over, :3] *= (step_cap / norms[over])[:, None]
    if total is not None:
        proposed = total + correction[:, :3]
        norms = np.sqrt(np.einsum("ij,ij->i", proposed, proposed))
        over = norms > norm_cap
        if over.any():
            proposed[over] *= (norm_cap / norms[over])[:, None]
            correction[:, :3] = proposed - total
        total[:] = proposed


def _component_minimum(n: int, src: IntArray, dst: IntArray) -> IntArray:
    """Return, for every experience, the lowest id of its connected component (a flat union-find parent)."""
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    graph = sp.csr_matrix((np.ones(src.size), (src, dst)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    first = np.full(int(labels.max()) + 1, n, dtype=np.int64)
    np.minimum.at(first, labels, np.arange(n, dtype=np.int64))
    return first[labels]


def _last_loop_from(src: IntArray, kind: Int8Array, start: IntArray, before: IntArray) -> IntArray:
    """Return, per pair, the index of the last loop link leaving ``start[i]`` below ``before[i]``, or −1.

    Links are numbered in the order they were made, so this is the closure the robot made from the
    experience it created last before relocalising.
    """
    loops = np.flatnonzero(kind == int(LinkKind.LOOP))
    if not loops.size or not start.size:
        return np.full(start.size, -1, dtype=np.int64)
    stride = src.size + 1
    keys = src[loops] * stride + loops
    order = np.argsort(keys)  # by (source, index): keys are distinct
    keys, loops = keys[order], loops[order]
    at = np.searchsorted(keys, start * stride + before) - 1  # the last key below (start, before)
    found = loops[np.maximum(at, 0)]
    return np.where((at >= 0) & (src[found] == start), found, -1)

"""Experience map: a semi-metric graph of SE(3) experiences with relaxation.

OpenRatSLAM's ``ExperienceMap`` (Ball et al. 2013; anchors §1.1; Menezes et al.
Eqs. 6–8) generalised to 4-DoF motion (x, y, z, yaw) as PoseidonSLAM's 3-D graph
(thesis Eqs. 4.20–4.21, with the clamps ``max_correction_norm`` and
``max_correction_step``). Poses are stored as (x, y, z, yaw); the quaternion is
the rotation ``yaw`` about z (roll and pitch are not represented).

A link holds the pose of its ``to`` experience in the frame of its ``from``
experience: translation (dx, dy, dz) and heading change dyaw — OpenRatSLAM's
``d``, ``heading_rad``, ``facing_rad`` written as a transform — plus Δt and the
Euclidean distance.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from enum import IntEnum
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from core._buffers import GrowBuffer
from core.lattice import wrap_angle, wrap_scalar

if TYPE_CHECKING:
    from core.config import Params
    from core.motion import Motion


class LinkKind(IntEnum):
    """Why a link exists (stored as int8)."""

    ODOMETRY = 0
    LOOP = 1
    MERGE = 2
    MANUAL = 3


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
        self._from = GrowBuffer((), np.int64)
        self._to = GrowBuffer((), np.int64)
        self._transform = GrowBuffer((4,), np.float64)
        self._dt = GrowBuffer((), np.float64)
        self._distance = GrowBuffer((), np.float64)
        self._kind = GrowBuffer((), np.int8)
        self._pairs: set[tuple[int, int]] = set()
        self._exps_of_template: list[list[int]] = []
        self.current = -1
        self.previous = -1
        # dx, dy, dz (map frame), facing (rad), dt (s), distance (m) since the current experience
        self.accum = np.array([0.0, 0.0, 0.0, math.radians(params.exp_initial_em_deg), 0.0, 0.0])
        self.relax_pending = False
        self._operator: sp.csr_matrix | None = None

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
    def poses(self) -> np.ndarray:
        """Return experience poses (E, 4): x, y, z, yaw (view)."""
        return self._pose.view

    @property
    def lattice_coords(self) -> np.ndarray:
        """Return experience lattice coordinates (E, D) (view)."""
        return self._pc.view

    @property
    def templates(self) -> np.ndarray:
        """Return each experience's template id (E,) (view)."""
        return self._template.view

    @property
    def links(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Return (from, to, transform (K,4), dt, distance, kind) views."""
        return (
            self._from.view, self._to.view, self._transform.view, self._dt.view, self._distance.view, self._kind.view
        )

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
        facing = a[3]
        c, s = math.cos(facing), math.sin(facing)
        a[0] += c * motion.dx - s * motion.dy
        a[1] += s * motion.dx + c * motion.dy
        a[2] += motion.dz
        a[3] = wrap_scalar(facing + motion.dyaw)
        a[4] += motion.dt
        a[5] += math.sqrt(motion.dx * motion.dx + motion.dy * motion.dy + motion.dz * motion.dz)

    def create_experience(self, template: int, lattice: np.ndarray, stamp: float, origin: int) -> int:
        """Create an experience at the current one plus the accumulated odometry; link and select it.

        Menezes et al. Eq. 7 / OpenRatSLAM2 Eq. 7: p_j = p_i + Δp_ij. The first
        experience sits at the origin with the initial heading ``exp_initial_em_deg``.
        """
        a = self.accum
        if self.current < 0:
            pose = np.array([0.0, 0.0, 0.0, a[3]])
        else:
            base = self._pose.view[self.current]
            pose = np.array([base[0] + a[0], base[1] + a[1], base[2] + a[2], a[3]])
        new_id = self._pose.append(pose)
        self._pc.append(lattice)
        self._template.append(template)
        self._stamp.append(stamp)
        self._origin.append(origin)
        while len(self._exps_of_template) <= template:
            self._exps_of_template.append([])
        self._exps_of_template[template].append(new_id)
        if self.current >= 0:
            self.create_link(self.current, new_id, 0.0, LinkKind.ODOMETRY)
        self.set_experience(new_id, 0.0)
        return new_id

    def create_link(self, source: int, target: int, relative_rad: float, kind: LinkKind) -> bool:
        """Link ``source`` → ``target`` with the accumulated odometry; False if that link exists.

        OpenRatSLAM ``on_create_link``: the translation is expressed in the source's
        frame and the heading change includes the view's ``relative_rad``. A link to
        anything but a brand-new experience closes a loop: relaxation is scheduled.
        """
        if (source, target) in self._pairs or source == target:
            return False
        a = self.accum
        yaw = self._pose.view[source, 3]
        c, s = math.cos(yaw), math.sin(yaw)
        transform = (c * a[0] + s * a[1], -s * a[0] + c * a[1], a[2], wrap_scalar(a[3] + relative_rad - yaw))
        self._append_link(source, target, transform, a[4], math.sqrt(a[0] ** 2 + a[1] ** 2 + a[2] ** 2), kind)
        if kind != LinkKind.ODOMETRY and self.link_residual(self.link_count - 1) >= self.params.exp_relax_tolerance:
            self.relax_pending = True  # a consistent closure needs no relaxation
        return True

    def _append_link(
        self, source: int, target: int, transform: tuple[float, ...] | np.ndarray, dt: float, distance: float, kind: int
    ) -> None:
        self._from.append(source)
        self._to.append(target)
        self._transform.append(transform)
        self._dt.append(dt)
        self._distance.append(distance)
        self._kind.append(kind)
        self._pairs.add((source, target))
        self._operator = None

    def set_experience(self, experience: int, relative_rad: float) -> None:
        """Make ``experience`` current and restart the accumulators (OpenRatSLAM ``on_set_experience``)."""
        self.previous = self.current
        self.current = experience
        self.accum[:] = 0.0
        self.accum[3] = wrap_scalar(float(self._pose.view[experience, 3]) + relative_rad)

    # ------------------------------------------------------------ relaxation
    def _relaxation_operator(self) -> sp.csr_matrix:
        """Return the (E, K) sparse map from link residuals to experience corrections, scaled by c/degree."""
        if self._operator is None:
            n = self.count
            k = self.link_count
            rows = np.concatenate([self._from.view, self._to.view])
            cols = np.concatenate([np.arange(k), np.arange(k)])
            degree = np.bincount(rows, minlength=n).astype(np.float64)
            degree[degree == 0] = 1.0
            vals = np.concatenate([np.ones(k), -np.ones(k)]) * (self.params.exp_correction / degree[rows])
            self._operator = sp.csr_matrix((vals, (rows, cols)), shape=(n, k))
        return self._operator

    def relax(self, iterations: int | None = None) -> int:
        """Relax the graph; return the number of iterations run.

        Eq. 8 of Menezes et al. (with the corrected incoming-link sign of thesis
        Eq. 4.21), in 3-D plus heading, applied simultaneously to every experience:
        for each link the residual r = p_to − (p_from + R(yaw_from)·t) moves the
        source by +c·r and the target by −c·r (c = ``exp_correction``), and the
        heading residual likewise. Each experience's summed correction is divided by
        its number of links, which keeps c = 0.5 stable at any degree (the printed
        sum is unstable for degree > 2 when applied simultaneously). Optional clamps
        (thesis §4.2.4): ``max_correction_step`` caps each experience's per-iteration
        correction norm and ``max_correction_norm`` its total correction in this call.
        Iteration stops early once the largest correction (metres or radians) is
        below ``exp_relax_tolerance``; then ``relax_pending`` is cleared.
        """
        p = self.params
        loops = p.exp_loops if iterations is None else iterations
        if self.link_count == 0 or loops <= 0:
            self.relax_pending = False
            return 0
        operator = self._relaxation_operator()
        src = self._from.view
        dst = self._to.view
        tx, ty, tz, tyaw = (np.ascontiguousarray(self._transform.view[:, i]) for i in range(4))
        pose = self._pose.view
        step_cap = p.max_correction_step
        norm_cap = p.max_correction_norm
        total = np.zeros((self.count, 3)) if norm_cap > 0 else None
        tol = p.exp_relax_tolerance
        residual = np.empty((src.shape[0], 4))
        run = 0
        for _ in range(loops):
            run += 1
            source = pose[src]
            target = pose[dst]
            cos_y = np.cos(source[:, 3])
            sin_y = np.sin(source[:, 3])
            residual[:, 0] = target[:, 0] - source[:, 0] - cos_y * tx + sin_y * ty
            residual[:, 1] = target[:, 1] - source[:, 1] - sin_y * tx - cos_y * ty
            residual[:, 2] = target[:, 2] - source[:, 2] - tz
            residual[:, 3] = np.remainder(target[:, 3] - source[:, 3] - tyaw + math.pi, 2.0 * math.pi) - math.pi
            correction = operator @ residual
            if step_cap > 0:
                norms = np.sqrt(np.einsum("ij,ij->i", correction[:, :3], correction[:, :3]))
                scale = np.minimum(1.0, step_cap / np.maximum(norms, 1e-300))
                correction[:, :3] *= scale[:, None]
            if total is not None:
                proposed = total + correction[:, :3]
                norms = np.linalg.norm(proposed, axis=1)
                over = norms > norm_cap
                if np.any(over):
                    proposed[over] *= (norm_cap / norms[over])[:, None]
                    correction[:, :3] = proposed - total
                total = proposed
            pose += correction
            largest = float(np.abs(correction).max())
            if largest < tol:
                self.relax_pending = False
                break
        pose[:, 3] = wrap_angle(pose[:, 3])
        return run

    def link_residual(self, link: int) -> float:
        """Return the largest absolute residual (m or rad) of one link under the current poses."""
        source = self._pose.view[self._from.view[link]]
        target = self._pose.view[self._to.view[link]]
        t = self._transform.view[link]
        c, s = math.cos(source[3]), math.sin(source[3])
        return max(
            abs(target[0] - source[0] - c * t[0] + s * t[1]),
            abs(target[1] - source[1] - s * t[0] - c * t[1]),
            abs(target[2] - source[2] - t[2]),
            abs(wrap_scalar(target[3] - source[3] - t[3])),
        )

    def add_link_raw(
        self, source: int, target: int, transform: np.ndarray, dt: float, distance: float, kind: LinkKind
    ) -> bool:
        """Add a link with an explicit transform (merges, manual links); schedules relaxation."""
        if (source, target) in self._pairs or source == target:
            return False
        self._append_link(source, target, np.asarray(transform, dtype=np.float64), dt, distance, int(kind))
        self.relax_pending = True
        return True

    # -------------------------------------------------------------- snapshot
    def snapshot(self) -> dict[str, np.ndarray]:
        """Return the map as plain arrays (keys ``em_*`` of docs/architecture.md)."""
        return {
            "em_pose": self._pose.copy(),
            "em_pc": self._pc.copy(),
            "em_template": self._template.copy(),
            "em_stamp": self._stamp.copy(),
            "em_origin": self._origin.copy(),
            "em_link_from": self._from.copy(),
            "em_link_to": self._to.copy(),
            "em_link_transform": self._transform.copy(),
            "em_link_dt": self._dt.copy(),
            "em_link_distance": self._distance.copy(),
            "em_link_kind": self._kind.copy(),
            "em_current": np.asarray(self.current, dtype=np.int64),
            "em_previous": np.asarray(self.previous, dtype=np.int64),
            "em_accum": self.accum.copy(),
            "em_relax_pending": np.asarray(self.relax_pending, dtype=bool),
        }

    @classmethod
    def restore(cls, params: Params, lattice_rank: int, state: Mapping[str, np.ndarray]) -> ExperienceMap:
        """Rebuild a map from :meth:`snapshot` arrays, exactly."""
        em = cls(params, lattice_rank)
        em._pose = GrowBuffer.from_array(np.asarray(state["em_pose"]).reshape(-1, 4), np.float64)
        em._pc = GrowBuffer.from_array(np.asarray(state["em_pc"]).reshape(-1, lattice_rank), np.float64)
        em._template = GrowBuffer.from_array(state["em_template"], np.int64)
        em._stamp = GrowBuffer.from_array(state["em_stamp"], np.float64)
        em._origin = GrowBuffer.from_array(state["em_origin"], np.int64)
        em._from = GrowBuffer.from_array(state["em_link_from"], np.int64)
        em._to = GrowBuffer.from_array(state["em_link_to"], np.int64)
        em._transform = GrowBuffer.from_array(np.asarray(state["em_link_transform"]).reshape(-1, 4), np.float64)
        em._dt = GrowBuffer.from_array(state["em_link_dt"], np.float64)
        em._distance = GrowBuffer.from_array(state["em_link_distance"], np.float64)
        em._kind = GrowBuffer.from_array(state["em_link_kind"], np.int8)
        em._pairs = set(zip(em._from.view.tolist(), em._to.view.tolist(), strict=True))
        templates = em._template.view
        n_templates = int(templates.max()) + 1 if templates.size else 0
        em._exps_of_template = [[] for _ in range(n_templates)]
        for exp_id, template in enumerate(templates.tolist()):
            em._exps_of_template[template].append(exp_id)
        em.current = int(state["em_current"])
        em.previous = int(state["em_previous"])
        em.accum = np.asarray(state["em_accum"], dtype=np.float64).copy()
        em.relax_pending = bool(state["em_relax_pending"])
        return em

"""DVL + IMU + depth fused into 4-DoF dead reckoning: a complementary filter (the engine's motion input).

An AUV's navigation (PoseidonSLAM's ``robot_state_node``; DolphinSLAM Eqs. 3.10–3.11: the DVL's velocity
rotated by the IMU's attitude and integrated) as a stated filter. The messages of the three sensors
(:mod:`mapserver.ingest.navigation`) are processed in stamp order (at equal stamps IMU, then DVL, then
depth); each one first **propagates** the state to its stamp, then **corrects** it. The state is the pose
``(x, y, z, ψ)`` in the navigation frame (z up, ψ counter-clockwise; x, y from the first estimate's origin),
the held body velocity ``v_b``, the held body rate ``ω_b`` and the tilt ``R_t`` (the IMU's roll and pitch).

Propagation over ``Δt`` (zero-order hold of ``v_b`` and ``ω_b``, Eq. 3.10 restricted to 4 DoF):

    u = R_t · v_b                       (forward u₁, lateral u₂, vertical u₃ in the level heading frame)
    r = (R_t · ω_b)_z                   (turn rate about the vertical)
    (δx, δy, δz, δψ) = arc(u₁, u₂, u₃, r, Δt)   (the exact circular arc of
                                          :func:`mapserver.ingest.odometry.arc_increment`)
    [x y]ᵀ += R(ψ) · [δx δy]ᵀ ,  z += δz ,  ψ += δψ     (Eq. 3.11, integrated exactly)

Corrections:

* **IMU orientation** ``q``: the body's attitude is ``R_wb = R(q) · M_imuᵀ`` (``M_imu`` the IMU's mounting),
  its yaw ``ψ_m = atan2(R_wb[1,0], R_wb[0,0])`` and its tilt ``R_t = R_z(−ψ_m) · R_wb``. The heading is the
  complementary blend of the integrated turn rate (high-passed) and the orientation's yaw (low-passed):

      ψ ← ψ + k_ψ · wrap(ψ_m − ψ),   k_ψ = 1 − exp(−Δt_ψ / τ_ψ)

  with ``Δt_ψ`` the time since the previous orientation and ``τ_ψ`` = :attr:`NavParams.heading_tau_s`
  (5 s). The first orientation sets ``ψ = ψ_m``; an IMU that never reports a rate has ``k_ψ = 1``.
* **IMU angular velocity** ``ω_i``: ``ω_b = M_imu · ω_i``.
* **DVL velocity** ``v_d``: ``v_b = M_dvl · v_d − ω_b × t_dvl`` (the DVL measures the velocity of its own
  point, ``t_dvl`` its lever arm). A **lost-bottom gap** leaves ``v_b`` as it was: the vehicle keeps its last
  measured velocity through the gap (a dropout is never read as a stop). Until the first valid message
  ``v_b = 0``.
* **Depth** ``z_m``: ``z ← z + k_z · (z_m − z)``, ``k_z = 1 − exp(−Δt_z / τ_z)``, ``τ_z`` =
  :attr:`NavParams.depth_tau_s` (0.5 s), ``Δt_z`` the time since the previous depth; the first depth sets
  ``z = z_m``. So the vertical motion is the depth sensor's, low-passed, with the DVL's vertical velocity
  bridging the samples. Without a depth topic, z is the integrated vertical velocity.

The filter emits an estimate (an :class:`~mapserver.ingest.odometry.OdometryState`) after each message once
it is initialised: a heading known (the first IMU message: its orientation, or ψ = 0 for a rate-only IMU)
and, when the log has a depth topic, a first depth. The reader differences these estimates at the camera
stamps (pose mode of :mod:`mapserver.ingest.odometry`, Eq. 4.15 of PoseidonSLAM) into each frame's
:class:`~core.motion.Motion`; the odometry checks (non-finite values, bounds) apply to them as to odometry
messages.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from core.angles import wrap_angle_exact
from mapserver.ingest.navigation import DepthSample, DvlSample, ImuSample, Mount, NavParams
from mapserver.ingest.odometry import OdometryState, arc_increment, quaternion_matrix, yaw_of_matrix

NS = 1e-9
NavSample = DvlSample | ImuSample | DepthSample
_ORDER = {ImuSample: 0, DvlSample: 1, DepthSample: 2}


@dataclass(slots=True)
class NavigationReport:
    """What the fusion read: messages per sensor, DVL lost-bottom gaps, where each mounting came from."""

    dvl_messages: int = 0
    dvl_gaps: int = 0
    imu_messages: int = 0
    depth_messages: int = 0
    depth_gaps: int = 0
    mounts: dict[str, str] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        """Return the counts and mount sources as JSON-ready values."""
        return {
            "dvl_messages": self.dvl_messages, "dvl_gaps": self.dvl_gaps, "imu_messages": self.imu_messages,
            "depth_messages": self.depth_messages, "depth_gaps": self.depth_gaps, "mounts": dict(self.mounts),
        }  # fmt: skip


class ComplementaryFilter:
    """The filter of the module docstring; :meth:`update` one sample at a time, in stamp order."""

    def __init__(
        self, params: NavParams, dvl_mount: Mount, imu_mount: Mount, *, has_depth: bool,
        report: NavigationReport | None = None,
    ) -> None:  # fmt: skip
        self.params = params
        self.dvl_mount, self.imu_mount = dvl_mount, imu_mount
        self.has_depth = has_depth
        self.report = report or NavigationReport()
        self.x = self.y = self.z = self.yaw = 0.0
        self.tilt = np.eye(3)
        self.velocity = np.zeros(3)
        self.rate = np.zeros(3)
        self.gyro_seen = False
        self.heading_ready = False
        self.depth_ready = False
        self.t_ns: int | None = None
        self.t_heading: int | None = None
        self.t_depth: int | None = None

    @property
    def ready(self) -> bool:
        """True once a heading (and a depth, with a depth topic) is known."""
        return self.heading_ready and (self.depth_ready or not self.has_depth)

    def propagate(self, t_ns: int) -> None:
        """Integrate the held velocity and rate from the last stamp to ``t_ns`` (exact arcs)."""
        if self.t_ns is not None and t_ns > self.t_ns:
            u = self.tilt @ self.velocity
            r = float((self.tilt @ self.rate)[2])
            dx, dy, dz, dyaw = arc_increment(float(u[0]), float(u[1]), float(u[2]), r, (t_ns - self.t_ns) * NS)
            c, s = math.cos(self.yaw), math.sin(self.yaw)
            self.x += c * dx - s * dy
            self.y += s * dx + c * dy
            self.z += dz
            self.yaw += dyaw
        if self.t_ns is None or t_ns > self.t_ns:
            self.t_ns = t_ns

    def update(self, sample: NavSample) -> OdometryState | None:
        """Propagate to the sample's stamp, apply it; return the estimate (None before initialisation)."""
        self.propagate(sample.stamp_ns)
        if isinstance(sample, ImuSample):
            self._imu(sample)
        elif isinstance(sample, DvlSample):
            self._dvl(sample)
        else:
            self._depth(sample)
        return self.state() if self.ready else None

    def _imu(self, sample: ImuSample) -> None:
        self.report.imu_messages += 1
        mount = self.imu_mount.rotation
        if sample.angular_velocity is not None:
            self.rate = mount @ np.asarray(sample.angular_velocity, dtype=float)
            self.gyro_seen = True
        if sample.orientation is not None:
            attitude = quaternion_matrix(*sample.orientation) @ mount.T
            measured = yaw_of_matrix(attitude)
            c, s = math.cos(measured), math.sin(measured)
            self.tilt = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ attitude
            if not self.heading_ready or not self.gyro_seen or self.t_heading is None:
                gain = 1.0
            else:
                gain = 1.0 - math.exp(-(sample.stamp_ns - self.t_heading) * NS / self.params.heading_tau_s)
            self.yaw += gain * wrap_angle_exact(measured - self.yaw)
            self.t_heading = sample.stamp_ns
        self.heading_ready = self.heading_ready or sample.orientation is not None or sample.angular_velocity is not None

    def _dvl(self, sample: DvlSample) -> None:
        self.report.dvl_messages += 1
        if sample.velocity is None:
            self.report.dvl_gaps += 1
            return
        measured = self.dvl_mount.rotation @ np.asarray(sample.velocity, dtype=float)
        self.velocity = measured - np.cross(self.rate, self.dvl_mount.translation)

    def _depth(self, sample: DepthSample) -> None:
        self.report.depth_messages += 1
        if sample.z is None:
            self.report.depth_gaps += 1
            return
        if not self.depth_ready or self.t_depth is None:
            self.z = sample.z
        else:
            gain = 1.0 - math.exp(-(sample.stamp_ns - self.t_depth) * NS / self.params.depth_tau_s)
            self.z += gain * (sample.z - self.z)
        self.depth_ready = True
        self.t_depth = sample.stamp_ns

    def state(self) -> OdometryState:
        """Return the current estimate (pose; the held level-frame velocity and turn rate as its twist)."""
        u = self.tilt @ self.velocity
        assert self.t_ns is not None
        return OdometryState(
            stamp_ns=self.t_ns, x=self.x, y=self.y, z=self.z, yaw=self.yaw, forward=float(u[0]),
            lateral=float(u[1]), vertical=float(u[2]), yaw_rate=float((self.tilt @ self.rate)[2]),
        )  # fmt: skip


def merge_samples(*streams: Iterable[NavSample]) -> Iterator[NavSample]:
    """Merge stamp-ordered sample streams by stamp (IMU, then DVL, then depth at equal stamps)."""
    return heapq.merge(*streams, key=lambda s: (s.stamp_ns, _ORDER[type(s)]))


def fuse(samples: Iterable[NavSample], nav_filter: ComplementaryFilter) -> Iterator[OdometryState]:
    """Run the filter over merged samples; yield every estimate after initialisation."""
    for sample in samples:
        state = nav_filter.update(sample)
        if state is not None:
            yield state

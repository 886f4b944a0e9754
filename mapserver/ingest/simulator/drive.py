"""A simulated drive along a route: true trajectory, ground truth, noisy odometry and camera stamps.

True motion. The vehicle follows its route at a nominal speed with a smooth speed variation, a smooth
lateral offset from the route (so every visit of a place is a little different) and, for underwater
vehicles, a depth profile along the route plus a smooth depth wobble. Smooth variations are sums of
sinusoids with random frequencies (periods of 5 to 40 s) and phases, evaluated exactly at any time. The
heading is the direction of travel. A session may begin with an in-place turn (``turn_deg``): the vehicle
starts facing ``turn_deg`` away from the route and turns onto it, so its odometry frame (and the map frame
built from it) is rotated by that angle compared with a start already facing along the route.

Odometry (``nav_msgs/Odometry`` at ``odom_hz``). For each interval between two odometry stamps the true
body-frame twist is the constant (forward, lateral, vertical speed, yaw rate) whose exact arc integration
(zero-order hold, as the log reader integrates) reproduces the true relative motion. The published twist
is that twist corrupted as a wheel or DVL odometry would be: forward and lateral speed scaled by
``1 + scale_error``, a yaw-rate bias, a constant vertical-speed bias, and white noise on every component;
the published pose is the integral of the published twist from the origin (the usual odometry frame). So
raw odometry drifts: after a lap the loop does not close. Ground truth is the true pose, in the world
frame, at every odometry stamp.

Error model: systematic odometry errors are properties of the *vehicle* (:class:`VehicleErrors`: the
wheel-radius or DVL scale error, the repeatable yaw-rate bias of the gyro or of unequal wheel radii, the
vertical-speed bias), shared by every session the vehicle drives; a scenario draws them once (its
sessions are one robot's missions). Each session adds its own smaller random effects (Noise fields
``session_*``): a scale change (tyre pressure, load, water properties), a turn-on yaw-rate bias offset,
and an in-run yaw-rate bias random walk (gyro bias instability), plus the white noise. A drive simulated
without a vehicle (``simulate_drive(..., vehicle=None)``) is its own vehicle, drawn from the session's
generator.

Camera stamps run at ``camera_hz`` from ``camera_offset_s`` after the first odometry stamp, so images and
odometry are not simultaneous. Each frame carries the lighting gain of this visit (constant per session,
plus a slow drift of a fraction of a percent).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from core.se3 import quaternion_from_yaw
from mapserver.ingest.frames import PoseSample
from mapserver.ingest.simulator.routes import Route
from mapserver.ingest.writer import OdomSample

FloatArray = npt.NDArray[np.float64]

_SMALL = 1e-9


@dataclass(frozen=True)
class Rates:
    """Message rates.

    Attributes:
        camera_hz: image rate.
        odom_hz: odometry and ground-truth rate.
        camera_offset_s: delay of the first image after the first odometry message.

    """

    camera_hz: float = 1.0
    odom_hz: float = 10.0
    camera_offset_s: float = 0.037


@dataclass(frozen=True)
class Noise:
    """Per-visit variation and sensor noise (magnitudes; signs are drawn per session).

    Attributes:
        lateral_m: standard deviation of the smooth lateral offset from the route (m).
        speed_variation: relative amplitude of the smooth speed variation.
        depth_m: standard deviation of the smooth depth wobble (m), underwater only.
        scale_error: the vehicle's odometry speed scale error magnitude (fraction).
        yaw_bias: the vehicle's odometry yaw-rate bias magnitude (rad/s).
        vz_bias: the vehicle's odometry vertical-speed bias magnitude (m/s).
        session_scale_error: standard deviation of a session's own scale change (fraction).
        session_yaw_bias: standard deviation of a session's turn-on yaw-rate bias offset (rad/s).
        session_yaw_walk: intensity of a session's yaw-rate bias random walk (rad/s per √s).
        speed_noise: white noise on the forward speed (m/s, per message).
        yaw_noise: white noise on the yaw rate (rad/s, per message).
        vz_noise: white noise on the vertical speed (m/s, per message).
        gain: standard deviation of the lighting gain of a visit (fraction).
        pixel_noise: standard deviation of the pixel noise (grey levels).

    """

    lateral_m: float = 0.12
    speed_variation: float = 0.08
    depth_m: float = 0.0
    scale_error: float = 0.025
    yaw_bias: float = 0.004
    vz_bias: float = 0.0
    session_scale_error: float = 0.0
    session_yaw_bias: float = 0.0
    session_yaw_walk: float = 0.0
    speed_noise: float = 0.03
    yaw_noise: float = 0.02
    vz_noise: float = 0.0
    gain: float = 0.03
    pixel_noise: float = 2.0

    def scaled(self, factor: float) -> Noise:
        """Return the noise with its lengths scaled by ``factor`` (for a scaled-down world)."""
        return Noise(
            lateral_m=self.lateral_m * factor,
            speed_variation=self.speed_variation,
            depth_m=self.depth_m * factor,
            scale_error=self.scale_error,
            yaw_bias=self.yaw_bias,
            vz_bias=self.vz_bias * factor,
            session_scale_error=self.session_scale_error,
            session_yaw_bias=self.session_yaw_bias,
            session_yaw_walk=self.session_yaw_walk,
            speed_noise=self.speed_noise * factor,
            yaw_noise=self.yaw_noise,
            vz_noise=self.vz_noise * factor,
            gain=self.gain,
            pixel_noise=self.pixel_noise,
        )


@dataclass(frozen=True)
class VehicleErrors:
    """The systematic odometry errors of one vehicle, shared by all the sessions it drives.

    Attributes:
        scale_error: speed scale error (fraction; wheel radius, DVL scale factor).
        yaw_bias: repeatable yaw-rate bias (rad/s; gyro bias, unequal wheel radii at cruising speed).
        vz_bias: vertical-speed bias (m/s).

    """

    scale_error: float = 0.0
    yaw_bias: float = 0.0
    vz_bias: float = 0.0

    @classmethod
    def draw(cls, noise: Noise, rng: np.random.Generator) -> VehicleErrors:
        """Return a vehicle with the magnitudes of ``noise`` and random signs."""
        return cls(
            scale_error=_sign(rng) * noise.scale_error,
            yaw_bias=_sign(rng) * noise.yaw_bias,
            vz_bias=_sign(rng) * noise.vz_bias,
        )


@dataclass(frozen=True)
class DriveSpec:
    """What one session drives.

    Attributes:
        route: the route.
        start_m: arc length where the session starts.
        distance_m: arc length it covers.
        speed: nominal speed (m/s).
        depth: vehicle z as a function of the route arc length (vectorised), or None for z = 0.
        turn_deg: initial in-place turn (see the module docstring).
        turn_rate: yaw rate of that turn (rad/s).

    """

    route: Route
    start_m: float
    distance_m: float
    speed: float
    depth: Callable[[FloatArray], FloatArray] | None = None
    turn_deg: float = 0.0
    turn_rate: float = 0.3


class Smooth:
    """A smooth zero-mean random function of time: a sum of sinusoids, unit standard deviation."""

    def __init__(self, rng: np.random.Generator, terms: int = 6, period: tuple[float, float] = (5.0, 40.0)) -> None:
        self.freq = 2.0 * math.pi / rng.uniform(period[0], period[1], terms)
        self.phase = rng.uniform(0.0, 2.0 * math.pi, terms)
        self.amp = rng.uniform(0.5, 1.0, terms)
        self.amp *= math.sqrt(2.0) / math.sqrt(float(np.sum(self.amp**2)))

    def value(self, t: FloatArray) -> FloatArray:
        """Return f(t)."""
        return np.sin(np.multiply.outer(t, self.freq) + self.phase) @ self.amp

    def rate(self, t: FloatArray) -> FloatArray:
        """Return f'(t)."""
        return np.cos(np.multiply.outer(t, self.freq) + self.phase) @ (self.amp * self.freq)

    def integral(self, t: FloatArray) -> FloatArray:
        """Return ∫₀ᵗ f."""
        return (np.cos(self.phase) - np.cos(np.multiply.outer(t, self.freq) + self.phase)) @ (self.amp / self.freq)


class Trajectory:
    """The true continuous trajectory of one drive (see the module docstring)."""

    def __init__(self, spec: DriveSpec, noise: Noise, rng: np.random.Generator) -> None:
        self.spec = spec
        self.noise = noise
        self.speed_var = Smooth(rng)
        self.lateral = Smooth(rng)
        self.depth_wobble = Smooth(rng)
        self.turn_s = abs(math.radians(spec.turn_deg)) / spec.turn_rate
        amplitude = min(noise.speed_variation, 0.5)
        self._amp = amplitude / math.sqrt(2.0)
        # drive time needed to cover distance_m (speed variation integrates to a bounded offset)
        self.drive_s = self._time_for(spec.distance_m)
        self.duration = self.turn_s + self.drive_s

    def _arc(self, tau: FloatArray) -> FloatArray:
        sp = self.spec
        return sp.speed * (tau + self._amp * self.speed_var.integral(tau))

    def _time_for(self, distance: float) -> float:
        lo, hi = 0.0, distance / self.spec.speed * 2.0 + 10.0
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            if float(self._arc(np.asarray(mid))) < distance:
                lo = mid
            else:
                hi = mid
        return 0.5 * (lo + hi)

    def pose(self, t: npt.ArrayLike) -> FloatArray:
        """Return (N, 4) true poses (x, y, z, yaw) at session times ``t`` (s); yaw is continuous."""
        sp, route = self.spec, self.spec.route
        tt = np.atleast_1d(np.asarray(t, dtype=np.float64))
        tau = np.clip(tt - self.turn_s, 0.0, self.drive_s)
        s = sp.start_m + self._arc(tau)
        ds = sp.speed * (1.0 + self._amp * self.speed_var.value(tau))
        lat = self.noise.lateral_m * self.lateral.value(tau)
        dlat = self.noise.lateral_m * self.lateral.rate(tau)
        xy = route.position(s) + lat[:, None] * route.normal(s)
        yaw = route.heading(s) + np.arctan2(dlat, ds)
        turning = tt < self.turn_s
        if np.any(turning):
            remaining = math.radians(self.spec.turn_deg) * (1.0 - np.clip(tt / max(self.turn_s, _SMALL), 0.0, 1.0))
            yaw = np.where(turning, yaw - remaining, yaw)
        if sp.depth is None:
            z = np.zeros_like(s)
        else:
            z = np.asarray(sp.depth(s), dtype=np.float64) + self.noise.depth_m * self.depth_wobble.value(tau)
        return np.column_stack([xy, z, yaw])


@dataclass(frozen=True)
class Drive:
    """A simulated session, ready to render and write.

    Attributes:
        odometry: odometry messages.
        ground_truth: true poses at the odometry stamps (world frame).
        frame_stamps_ns: camera stamps.
        frame_poses: (F, 4) true camera-vehicle poses (x, y, z, yaw) at the camera stamps.
        frame_gain: (F,) lighting gain of each frame.
        true_poses: (N, 4) true poses at the odometry stamps.
        odom_poses: (N, 4) published odometry poses (x, y, z, yaw) in the odometry frame.
        errors: this session's odometry errors: scale_error and yaw_bias (the vehicle's plus the
            session's own offsets; the yaw-rate bias random walk comes on top), vz_bias.

    """

    odometry: list[OdomSample]
    ground_truth: list[PoseSample]
    frame_stamps_ns: npt.NDArray[np.int64]
    frame_poses: FloatArray
    frame_gain: FloatArray
    true_poses: FloatArray
    odom_poses: FloatArray
    errors: dict[str, float]


def body_twist(poses: FloatArray, dt: float) -> FloatArray:
    """Return the (N−1, 4) constant twists (v, u, vz, w) reproducing each step between consecutive poses.

    For a step of duration ``dt`` with relative motion (dx, dy) in the first pose's frame, heading change
    θ and height change dz: ``w = θ/dt``, ``vz = dz/dt`` and (v, u) solve
    ``(A·v − B·u, B·v + A·u) = (dx, dy)`` with ``A = sin θ / w``, ``B = (1 − cos θ)/w`` (the exact arc of
    :func:`mapserver.ingest.odometry.arc_increment`; series expansions for small θ).
    """
    p = np.asarray(poses, dtype=np.float64)
    d = np.diff(p, axis=0)
    c, s = np.cos(p[:-1, 3]), np.sin(p[:-1, 3])
    dx = c * d[:, 0] + s * d[:, 1]
    dy = -s * d[:, 0] + c * d[:, 1]
    theta = d[:, 3]
    small = np.abs(theta) < 1e-4
    t2 = theta * theta
    with np.errstate(divide="ignore", invalid="ignore"):
        a_big = np.sin(theta) / theta * dt
        b_big = (1.0 - np.cos(theta)) / theta * dt
    a = np.where(small, dt * (1.0 - t2 / 6.0 + t2 * t2 / 120.0), a_big)
    b = np.where(small, dt * theta * (0.5 - t2 / 24.0 + t2 * t2 / 720.0), b_big)
    det = a * a + b * b
    v = (a * dx + b * dy) / det
    u = (a * dy - b * dx) / det
    return np.column_stack([v, u, d[:, 2] / dt, theta / dt])


def integrate(twists: FloatArray, dt: float) -> FloatArray:
    """Integrate constant twists (v, u, vz, w) over steps of ``dt`` from the origin; return (N+1, 4) poses."""
    tw = np.asarray(twists, dtype=np.float64)
    theta = tw[:, 3] * dt
    t2 = theta * theta
    small = np.abs(theta) < 1e-4
    with np.errstate(divide="ignore", invalid="ignore"):
        a_big = np.sin(theta) / tw[:, 3]
        b_big = (1.0 - np.cos(theta)) / tw[:, 3]
    a = np.where(small, dt * (1.0 - t2 / 6.0 + t2 * t2 / 120.0), a_big)
    b = np.where(small, dt * theta * (0.5 - t2 / 24.0 + t2 * t2 / 720.0), b_big)
    lx = a * tw[:, 0] - b * tw[:, 1]
    ly = b * tw[:, 0] + a * tw[:, 1]
    yaw = np.concatenate([[0.0], np.cumsum(theta)])
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    x = np.concatenate([[0.0], np.cumsum(c * lx - s * ly)])
    y = np.concatenate([[0.0], np.cumsum(s * lx + c * ly)])
    z = np.concatenate([[0.0], np.cumsum(tw[:, 2] * dt)])
    return np.column_stack([x, y, z, yaw])


def _sign(rng: np.random.Generator) -> float:
    return 1.0 if rng.random() < 0.5 else -1.0


def simulate_drive(
    spec: DriveSpec,
    noise: Noise,
    rates: Rates,
    t0_ns: int,
    rng: np.random.Generator,
    vehicle: VehicleErrors | None = None,
) -> Drive:
    """Simulate one session (see the module docstring).

    Args:
        spec: route, start, distance, speed, depth profile, initial turn.
        noise: variation and sensor noise.
        rates: camera and odometry rates.
        t0_ns: stamp of the first odometry message.
        rng: the session's random generator (everything random about the session is drawn from it).
        vehicle: the vehicle's systematic odometry errors; None draws them from ``rng`` (a vehicle
            of its own).

    Returns:
        The drive.

    """
    traj = Trajectory(spec, noise, rng)
    dt = 1.0 / rates.odom_hz
    n = math.floor(traj.duration * rates.odom_hz) + 1
    t = np.arange(n) * dt
    true = traj.pose(t)
    twist = body_twist(true, dt)
    errors, walk = _session_errors(noise, vehicle, twist.shape[0], dt, rng)
    measured = _measured_twist(twist, spec, noise, errors, walk, rng)
    odom = integrate(measured, dt)
    stamps = t0_ns + np.rint(t * 1e9).astype(np.int64)
    odometry = _odometry_messages(stamps, odom, measured)
    ground_truth = _ground_truth_messages(stamps, true)
    frame_t, frame_stamps, gain = _camera_frames(rates, noise, float(t[-1]), t0_ns, rng)
    return Drive(
        odometry=odometry,
        ground_truth=ground_truth,
        frame_stamps_ns=frame_stamps,
        frame_poses=traj.pose(frame_t),
        frame_gain=gain,
        true_poses=true,
        odom_poses=odom,
        errors=errors,
    )


def _session_errors(
    noise: Noise, vehicle: VehicleErrors | None, m: int, dt: float, rng: np.random.Generator
) -> tuple[dict[str, float], FloatArray]:
    """Return the session's odometry errors (vehicle's plus session's own) and its (m,) yaw-rate bias walk."""
    if vehicle is None:
        vehicle = VehicleErrors.draw(noise, rng)
    session = rng.normal(0.0, 1.0, 2)  # the session's own scale change and turn-on yaw-rate bias offset
    scale = vehicle.scale_error + noise.session_scale_error * float(session[0])
    yaw_bias = vehicle.yaw_bias + noise.session_yaw_bias * float(session[1])
    walk = np.zeros(m)  # the session's yaw-rate bias random walk, from 0 at the start
    if m > 1:
        walk[1:] = np.cumsum(rng.normal(0.0, noise.session_yaw_walk * math.sqrt(dt), m - 1))
    return {"scale_error": scale, "yaw_bias": yaw_bias, "vz_bias": vehicle.vz_bias}, walk


def _measured_twist(
    twist: FloatArray,
    spec: DriveSpec,
    noise: Noise,
    errors: dict[str, float],
    walk: FloatArray,
    rng: np.random.Generator,
) -> FloatArray:
    """Return the (m, 4) twists (v, u, vz, w) the odometry publishes: the true ones with the session's errors."""
    m = twist.shape[0]
    scale, yaw_bias = errors["scale_error"], errors["yaw_bias"]
    moving = np.clip(np.abs(twist[:, 0]) / max(spec.speed, _SMALL), 0.0, 1.0)
    measured = np.empty_like(twist)
    measured[:, 0] = twist[:, 0] * (1.0 + scale) + moving * rng.normal(0.0, noise.speed_noise, m)
    measured[:, 1] = twist[:, 1] * (1.0 + scale)
    measured[:, 2] = twist[:, 2] + errors["vz_bias"] + rng.normal(0.0, 1.0, m) * noise.vz_noise
    measured[:, 3] = twist[:, 3] + yaw_bias + walk + rng.normal(0.0, noise.yaw_noise, m)
    if spec.depth is None:
        measured[:, 2] = 0.0
    return measured


def _odometry_messages(stamps: npt.NDArray[np.int64], odom: FloatArray, measured: FloatArray) -> list[OdomSample]:
    """Return the odometry messages: integrated pose and published twist at each stamp (the last at rest)."""
    published = np.vstack([measured, np.zeros((1, 4))])  # the last message: at rest
    return [
        OdomSample(int(stamps[k]), *(float(v) for v in odom[k]), *(float(v) for v in published[k]))
        for k in range(len(stamps))
    ]


def _ground_truth_messages(stamps: npt.NDArray[np.int64], true: FloatArray) -> list[PoseSample]:
    """Return the ground-truth messages: the true pose (yaw as a quaternion about z) at each stamp."""
    return [
        PoseSample(
            int(stamps[k]),
            float(true[k, 0]),
            float(true[k, 1]),
            float(true[k, 2]),
            *quaternion_from_yaw(true[k, 3]),
        )
        for k in range(len(stamps))
    ]


def _camera_frames(
    rates: Rates, noise: Noise, end_s: float, t0_ns: int, rng: np.random.Generator
) -> tuple[FloatArray, npt.NDArray[np.int64], FloatArray]:
    """Return the camera frames up to session time ``end_s``: their session times, stamps and lighting gains."""
    period = 1.0 / rates.camera_hz
    n_frames = math.floor((end_s - rates.camera_offset_s) / period) + 1
    frame_t = np.asarray(rates.camera_offset_s + np.arange(max(n_frames, 0)) * period, dtype=np.float64)
    frame_stamps = t0_ns + np.rint(frame_t * 1e9).astype(np.int64)
    session_gain = 1.0 + noise.gain * float(rng.normal())
    drift = Smooth(rng, period=(30.0, 120.0))
    gain = session_gain * (1.0 + 0.003 * drift.value(frame_t))
    return frame_t, frame_stamps, gain

"""An AUV's navigation sensors in the simulator: a DVL, an IMU and a pressure sensor, with ``/tf_static``.

Each sensor samples the session's true trajectory (:class:`~.drive.Trajectory`, rebuilt exactly from the
session's generator) at its own rate; the true velocities come from central differences of the trajectory
(±1 ms). The vehicle is 4-DoF (no roll or pitch): body velocity ``v_b = R_z(−ψ)·ṗ``, rate ``ω = (0, 0, ψ̇)``.

* **DVL** (``geometry_msgs/TwistWithCovarianceStamped`` on ``/robot/dvl/twist``, frame ``dvl_link``,
  ``dvl_hz``): mounted looking down (roll 180°) and turned 45° about its axis (a usual Janus mounting), at
  a lever arm from the body origin. It measures the velocity of its own point in its frame,
  ``v_d = Mᵀ·(v_b + ω × t)``, scaled by ``1 + scale error`` (magnitude ``dvl_scale_error``, sign drawn per
  vehicle) plus white noise ``dvl_noise``; its covariance diagonal is ``dvl_noise²``. **Bottom lock is lost**
  in bursts: a burst starts at a message with probability ``dvl_dropout`` and lasts a geometric number of
  messages of mean ``dvl_dropout_len``; a lost-bottom message carries a zero velocity **and a zero
  covariance** (the driver's "no fix").
* **IMU** (``sensor_msgs/Imu`` on ``/robot/imu``, frame ``imu_link`` mounted at the body's axes,
  ``imu_hz``): the orientation's yaw drifts, ``ψ_m = ψ + b_ψ·t + w(t) + n`` (constant drift ``imu_yaw_drift``
  rad/s with a drawn sign, a random walk of ``imu_yaw_walk`` rad/√s, white noise ``imu_yaw_noise``); the gyro
  reads ``ψ̇ + b_g + n`` (bias ``imu_gyro_bias`` with a drawn sign, noise ``imu_gyro_noise``). Linear
  acceleration is not simulated (covariance −1: not provided).
* **Pressure** (``sensor_msgs/FluidPressure`` on ``/robot/pressure``, ``depth_hz``):
  ``p = p₀ + ρ·g·(−z) + n`` with ``ρ`` = 1025 kg/m³, ``p₀`` = 101325 Pa, noise ``pressure_noise_pa``.
* ``/tf_static`` (``tf2_msgs/TFMessage``, one message at the start): ``base_link → dvl_link``,
  ``base_link → imu_link``, ``base_link → pressure_link``.

All draws come from a generator of their own (``[seed, 4000 + session index]``; the vehicle's signs from
``[seed, 4001]``), so adding these sensors changes nothing else of a session.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from core.se3 import quaternion_from_yaw
from mapserver.ingest.navigation import GRAVITY, rpy_matrix
from mapserver.ingest.simulator.drive import DriveSpec, Noise, Trajectory
from mapserver.ingest.writer import BODY_FRAME, TF_MESSAGE, ExtraMessage

FloatArray = npt.NDArray[np.float64]

DVL_TOPIC, IMU_TOPIC, PRESSURE_TOPIC = "/robot/dvl/twist", "/robot/imu", "/robot/pressure"
TF_STATIC_TOPIC = "/tf_static"
DVL_FRAME, IMU_FRAME, PRESSURE_FRAME = "dvl_link", "imu_link", "pressure_link"
WATER_DENSITY = 1025.0
ATMOSPHERIC_PA = 101325.0
_DIFF_S = 1e-3


@dataclass(frozen=True)
class NavSensors:
    """The navigation sensors' rates, mounting and errors (see the module docstring)."""

    dvl_hz: float = 5.0
    imu_hz: float = 20.0
    depth_hz: float = 10.0
    dvl_rpy_deg: tuple[float, float, float] = (180.0, 0.0, 45.0)
    dvl_xyz: tuple[float, float, float] = (-0.3, 0.0, -0.15)
    dvl_scale_error: float = 0.01
    dvl_noise: float = 0.005
    dvl_dropout: float = 0.03
    dvl_dropout_len: float = 4.0
    imu_yaw_drift: float = 2e-4
    imu_yaw_walk: float = 2e-4
    imu_yaw_noise: float = 0.003
    imu_gyro_bias: float = 5e-4
    imu_gyro_noise: float = 0.005
    pressure_noise_pa: float = 50.0

    def info(self) -> dict[str, Any]:
        """Return scenario.json's ``navigation`` entry (topics, rates, mounting and noise)."""
        return {
            "topics": {"dvl": DVL_TOPIC, "imu": IMU_TOPIC, "depth": PRESSURE_TOPIC, "tf_static": TF_STATIC_TOPIC},
            "water_density": WATER_DENSITY, "atmospheric_pa": ATMOSPHERIC_PA,
            **dataclasses.asdict(self),
        }  # fmt: skip


def _times(rate_hz: float, end_s: float, offset_s: float) -> FloatArray:
    n = math.floor((end_s - offset_s) * rate_hz) + 1
    return np.asarray(offset_s + np.arange(max(n, 0)) / rate_hz, dtype=np.float64)


def true_motion(traj: Trajectory, t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Return the true poses (N, 4), body velocities (N, 3) and yaw rates (N,) at session times ``t``."""
    pose = traj.pose(t)
    ahead, behind = traj.pose(t + _DIFF_S), traj.pose(np.maximum(t - _DIFF_S, 0.0))
    span = (t + _DIFF_S) - np.maximum(t - _DIFF_S, 0.0)
    rate = (ahead - behind) / span[:, None]
    c, s = np.cos(pose[:, 3]), np.sin(pose[:, 3])
    body = np.column_stack([c * rate[:, 0] + s * rate[:, 1], -s * rate[:, 0] + c * rate[:, 1], rate[:, 2]])
    return pose, body, rate[:, 3]


def _dropouts(rng: np.random.Generator, n: int, start: float, mean_len: float) -> npt.NDArray[np.bool_]:
    """Return which of ``n`` messages lost bottom lock (bursts: see the module docstring)."""
    lost = np.zeros(n, dtype=bool)
    k = 0
    starts, lengths = rng.random(n), rng.geometric(1.0 / max(mean_len, 1.0), n)
    while k < n:
        if starts[k] < start:
            lost[k : k + int(lengths[k])] = True
            k += int(lengths[k])
        else:
            k += 1
    return lost


def _signs(seed: int) -> FloatArray:
    rng = np.random.default_rng([seed, 4001])
    return np.where(rng.random(3) < 0.5, -1.0, 1.0)


def nav_messages(
    sensors: NavSensors, spec: DriveSpec, t0: int, noise: Noise, end_s: float, seed: int, index: int
) -> list[ExtraMessage]:
    """Return a session's DVL, IMU, pressure and ``/tf_static`` messages, in stamp order.

    Args:
        sensors: the sensors.
        spec: what the session drives; with ``noise``, ``seed`` and ``index`` its trajectory is rebuilt
            exactly as :func:`~mapserver.ingest.simulator.output.simulate_session` drew it.
        t0: the session's first stamp (ns).
        noise: the plan's noise.
        end_s: the session's last odometry time (s after ``t0``).
        seed: the scenario seed.
        index: the session's index in the plan.
    """
    traj = Trajectory(spec, noise, np.random.default_rng([seed, 1000 + index]))
    rng = np.random.default_rng([seed, 4000 + index])
    sign = _signs(seed)
    out: list[tuple[int, int, ExtraMessage]] = [(t0, 0, (t0, TF_STATIC_TOPIC, TF_MESSAGE, _tf_static(sensors, t0)))]
    out += [(m[0], 1, m) for m in _dvl(sensors, traj, end_s, t0, rng, sign[0])]
    out += [(m[0], 2, m) for m in _imu(sensors, traj, end_s, t0, rng, sign[1:])]
    out += [(m[0], 3, m) for m in _pressure(sensors, traj, end_s, t0, rng)]
    out.sort(key=lambda e: (e[0], e[1]))
    return [m for _s, _k, m in out]


def _stamps(t0_ns: int, t: FloatArray) -> list[int]:
    return (t0_ns + np.rint(t * 1e9).astype(np.int64)).tolist()


def _dvl(
    sensors: NavSensors, traj: Trajectory, end_s: float, t0_ns: int, rng: np.random.Generator, sign: float
) -> list[ExtraMessage]:
    t = _times(sensors.dvl_hz, end_s, 0.011)
    _pose, body, yaw_rate = true_motion(traj, t)
    lever = np.asarray(sensors.dvl_xyz)
    omega = np.column_stack([np.zeros_like(yaw_rate), np.zeros_like(yaw_rate), yaw_rate])
    point = body + np.cross(omega, lever)
    in_dvl = point @ rpy_matrix(*sensors.dvl_rpy_deg)  # Mᵀ·v for each row
    measured = in_dvl * (1.0 + sign * sensors.dvl_scale_error) + rng.normal(0.0, sensors.dvl_noise, in_dvl.shape)
    lost = _dropouts(rng, len(t), sensors.dvl_dropout, sensors.dvl_dropout_len)
    variance = sensors.dvl_noise**2
    out: list[ExtraMessage] = []
    for stamp, v, gap in zip(_stamps(t0_ns, t), measured, lost, strict=True):
        vel = (0.0, 0.0, 0.0) if gap else tuple(float(x) for x in v)
        out.append((stamp, DVL_TOPIC, "geometry_msgs/msg/TwistWithCovarianceStamped",
                    _twist_builder(stamp, vel, 0.0 if gap else variance)))  # fmt: skip
    return out


def _twist_builder(stamp: int, vel: tuple[float, ...], variance: float) -> Any:
    def build(m: Any) -> Any:
        t = m.types
        cov = np.zeros(36)
        cov[[0, 7, 14]] = variance
        twist = t["geometry_msgs/msg/Twist"](linear=m.vector(*vel), angular=m.vector(0.0, 0.0, 0.0))
        return t["geometry_msgs/msg/TwistWithCovarianceStamped"](
            header=m.header(stamp, DVL_FRAME),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=cov),
        )

    return build


def _imu(
    sensors: NavSensors, traj: Trajectory, end_s: float, t0_ns: int, rng: np.random.Generator, sign: FloatArray
) -> list[ExtraMessage]:
    t = _times(sensors.imu_hz, end_s, 0.0)
    pose, _body, yaw_rate = true_motion(traj, t)
    n = len(t)
    walk = np.concatenate([[0.0], np.cumsum(rng.normal(0.0, sensors.imu_yaw_walk / math.sqrt(sensors.imu_hz), n - 1))])
    yaw = pose[:, 3] + sign[0] * sensors.imu_yaw_drift * t + walk + rng.normal(0.0, sensors.imu_yaw_noise, n)
    rate = yaw_rate + sign[1] * sensors.imu_gyro_bias + rng.normal(0.0, sensors.imu_gyro_noise, n)
    out: list[ExtraMessage] = []
    for stamp, psi, w in zip(_stamps(t0_ns, t), yaw, rate, strict=True):
        out.append((stamp, IMU_TOPIC, "sensor_msgs/msg/Imu", _imu_builder(stamp, float(psi), float(w), sensors)))
    return out


def _imu_builder(stamp: int, yaw: float, rate: float, sensors: NavSensors) -> Any:
    def build(m: Any) -> Any:
        t = m.types
        q = quaternion_from_yaw(yaw)
        orientation_cov = np.diag([1e-4, 1e-4, sensors.imu_yaw_noise**2]).reshape(-1)
        rate_cov = np.diag([sensors.imu_gyro_noise**2] * 3).reshape(-1)
        accel_cov = np.zeros(9)
        accel_cov[0] = -1.0
        return t["sensor_msgs/msg/Imu"](
            header=m.header(stamp, IMU_FRAME),
            orientation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            orientation_covariance=orientation_cov,
            angular_velocity=m.vector(0.0, 0.0, rate),
            angular_velocity_covariance=rate_cov,
            linear_acceleration=m.vector(0.0, 0.0, 0.0),
            linear_acceleration_covariance=accel_cov,
        )

    return build


def _pressure(
    sensors: NavSensors, traj: Trajectory, end_s: float, t0_ns: int, rng: np.random.Generator
) -> list[ExtraMessage]:
    t = _times(sensors.depth_hz, end_s, 0.005)
    z = traj.pose(t)[:, 2]
    pressure = ATMOSPHERIC_PA + WATER_DENSITY * GRAVITY * (-z) + rng.normal(0.0, sensors.pressure_noise_pa, len(t))
    variance = sensors.pressure_noise_pa**2
    return [
        (stamp, PRESSURE_TOPIC, "sensor_msgs/msg/FluidPressure", _pressure_builder(stamp, float(p), variance))
        for stamp, p in zip(_stamps(t0_ns, t), pressure, strict=True)
    ]


def _pressure_builder(stamp: int, pressure: float, variance: float) -> Any:
    def build(m: Any) -> Any:
        return m.types["sensor_msgs/msg/FluidPressure"](
            header=m.header(stamp, PRESSURE_FRAME), fluid_pressure=pressure, variance=variance
        )

    return build


def _tf_static(sensors: NavSensors, stamp: int) -> Any:
    mounts = [
        (DVL_FRAME, sensors.dvl_xyz, sensors.dvl_rpy_deg),
        (IMU_FRAME, (0.0, 0.0, 0.05), (0.0, 0.0, 0.0)),
        (PRESSURE_FRAME, (0.2, 0.0, 0.1), (0.0, 0.0, 0.0)),
    ]

    def build(m: Any) -> Any:
        t = m.types
        transforms = []
        for child, xyz, rpy in mounts:
            q = _quaternion(rpy_matrix(*rpy))
            transforms.append(t["geometry_msgs/msg/TransformStamped"](
                header=m.header(stamp, BODY_FRAME), child_frame_id=child,
                transform=t["geometry_msgs/msg/Transform"](
                    translation=m.vector(*xyz),
                    rotation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
                ),
            ))  # fmt: skip
        return t[TF_MESSAGE](transforms=transforms)

    return build


def _quaternion(r: FloatArray) -> tuple[float, float, float, float]:
    """Return the unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method)."""
    trace = float(np.trace(r))
    if trace > 0.0:
        s = 2.0 * math.sqrt(trace + 1.0)
        return ((r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s)
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2.0 * math.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
    q = [0.0, 0.0, 0.0, 0.0]
    q[i] = 0.25 * s
    q[j] = (r[j, i] + r[i, j]) / s
    q[k] = (r[k, i] + r[i, k]) / s
    q[3] = (r[k, j] - r[j, k]) / s
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))

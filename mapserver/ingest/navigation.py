"""An AUV's navigation sensors as mapserver reads them: DVL, IMU and depth messages, and their mounting.

A vehicle without wheel odometry navigates on a Doppler velocity log (velocity over the seabed), an IMU
(orientation and turn rate) and a pressure or depth sensor. This module reduces each message to a sample;
:mod:`mapserver.ingest.fusion` fuses the samples into the motion the engine takes.

**DVL** (role ``dvl``): ``geometry_msgs/TwistWithCovarianceStamped``, ``geometry_msgs/TwistStamped`` or the
twist of a ``nav_msgs/Odometry``; the linear velocity is in the DVL's frame (``header.frame_id``; for
``Odometry`` its ``child_frame_id``, the frame its twist is given in). A **lost-bottom** message (no bottom
lock) is a *gap*, never a zero velocity (the fusion holds the last velocity across it):

* a velocity component that is NaN or ±inf;
* a covariance whose first entry is −1 (the ROS convention for "no estimate");
* a covariance whose linear block (diagonal entries 0, 7, 14) is all zero, **when the topic's other messages
  carry a covariance** (some message of the topic has a non-zero linear diagonal): a driver that reports its
  covariance and sends zero has no fix. A driver that never fills the covariance (all zero throughout)
  loses no message this way.

**IMU** (role ``imu``): ``sensor_msgs/Imu``; the orientation (absent when ``orientation_covariance[0]`` is
−1, the message definition's convention, or the quaternion is zero or not finite) and/or the angular velocity
(absent when ``angular_velocity_covariance[0]`` is −1 or it is not finite), in the IMU's frame
(``header.frame_id``). The orientation is the IMU frame's in a z-up (ENU) world frame (REP 103).

**Depth** (role ``depth``): ``sensor_msgs/FluidPressure``, converted to depth with a stated water density
ρ and atmospheric pressure p₀ (:class:`NavParams`): ``depth = (p − p₀) / (ρ·g)`` (hydrostatic; ``p`` in
pascal as the message defines it), the vehicle's z being ``−depth`` (z up, 0 at the surface); or
``geometry_msgs/PoseWithCovarianceStamped``, whose ``pose.position.z`` is the vehicle's z (z up). A non-finite
value is a gap.

**Mounting** (sensor to body): from ``/tf_static`` (``tf2_msgs/TFMessage``) when the log has one that holds
the sensor's frame: the transforms are chained from the sensor frame up to the body frame
(:attr:`NavParams.body_frame`, ``base_link``) or, when the tree does not hold it, to the root of the sensor's
tree; a sensor whose frame is the body frame is mounted at the identity. Otherwise the parameters
(:attr:`NavParams.dvl_rpy_deg`, ``dvl_xyz``, ``imu_rpy_deg``) give it. The body frame is x forward, y left,
z up (REP 103).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np
import numpy.typing as npt

from core.config import ConfigError
from mapserver.ingest.odometry import quaternion_matrix

FloatArray = npt.NDArray[np.float64]
Vector = tuple[float, float, float]

TWIST_COV_TYPE = "geometry_msgs/msg/TwistWithCovarianceStamped"
TWIST_TYPE = "geometry_msgs/msg/TwistStamped"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
IMU_TYPE = "sensor_msgs/msg/Imu"
PRESSURE_TYPE = "sensor_msgs/msg/FluidPressure"
POSE_COV_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF_TYPE = "tf2_msgs/msg/TFMessage"
TF_STATIC_TOPIC = "/tf_static"
DVL_TYPES = frozenset({TWIST_COV_TYPE, TWIST_TYPE, ODOMETRY_TYPE})
IMU_TYPES = frozenset({IMU_TYPE})
DEPTH_TYPES = frozenset({PRESSURE_TYPE, POSE_COV_TYPE})
GRAVITY = 9.80665
"""Standard gravity (m/s²)."""


@dataclass(frozen=True, slots=True)
class NavParams:
    """The stated constants of the navigation inputs and of the filter (:mod:`mapserver.ingest.fusion`).

    Attributes:
        water_density: ρ in kg/m³ (1025: sea water; 1000: fresh water).
        atmospheric_pa: p₀, the pressure at the surface, in Pa (101325: one standard atmosphere).
        gravity: g in m/s².
        heading_tau_s: τ_ψ, the complementary filter's heading time constant: the IMU's orientation yaw
            corrects the integrated turn rate with a first-order low-pass of this time constant.
        depth_tau_s: τ_z, the time constant with which the depth sensor corrects the integrated vertical
            velocity.
        body_frame: the body frame's name in ``/tf_static``.
        dvl_rpy_deg: the DVL's mounting (roll, pitch, yaw in degrees, body ← DVL) when ``/tf_static`` lacks it.
        dvl_xyz: the DVL's position in the body frame (m; its lever arm) when ``/tf_static`` lacks it.
        imu_rpy_deg: the IMU's mounting (roll, pitch, yaw in degrees, body ← IMU) when ``/tf_static`` lacks it.
    """

    water_density: float = 1025.0
    atmospheric_pa: float = 101325.0
    gravity: float = GRAVITY
    heading_tau_s: float = 5.0
    depth_tau_s: float = 0.5
    body_frame: str = "base_link"
    dvl_rpy_deg: Vector = (0.0, 0.0, 0.0)
    dvl_xyz: Vector = (0.0, 0.0, 0.0)
    imu_rpy_deg: Vector = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        positive = {"water_density": self.water_density, "gravity": self.gravity,
                    "heading_tau_s": self.heading_tau_s, "depth_tau_s": self.depth_tau_s}  # fmt: skip
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0.0):
                msg = f"navigation parameter {name} must be a positive number, got {value!r}"
                raise ConfigError(msg)
        numbers = (self.atmospheric_pa, *self.dvl_rpy_deg, *self.dvl_xyz, *self.imu_rpy_deg)
        if not all(math.isfinite(v) for v in numbers):
            msg = "navigation parameters must be finite numbers"
            raise ConfigError(msg)

    def as_dict(self) -> dict[str, Any]:
        """Return the parameters as JSON-ready values."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


def parse_nav_params(values: Mapping[str, str]) -> NavParams:
    """Return :class:`NavParams` from ``KEY=VALUE`` pairs (vectors as ``a:b:c``).

    Raises:
        ConfigError: an unknown key or a value that is not a number (or three).
    """
    known = {f.name: f for f in fields(NavParams)}
    kwargs: dict[str, Any] = {}
    for key, text in values.items():
        if key not in known:
            msg = f"unknown navigation parameter {key!r} (known: {', '.join(known)})"
            raise ConfigError(msg)
        if key == "body_frame":
            kwargs[key] = text
            continue
        try:
            parts = [float(p) for p in text.split(":")]
        except ValueError:
            parts = []
        vector = key.endswith(("_deg", "_xyz"))
        if len(parts) != (3 if vector else 1):
            msg = f"navigation parameter {key!r} needs {'three numbers a:b:c' if vector else 'a number'}, got {text!r}"
            raise ConfigError(msg)
        kwargs[key] = tuple(parts) if vector else parts[0]
    return NavParams(**kwargs)


# -- samples ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class DvlSample:
    """One DVL message: the velocity in the DVL frame, None for a lost-bottom gap."""

    stamp_ns: int
    frame_id: str
    velocity: Vector | None


@dataclass(frozen=True, slots=True)
class ImuSample:
    """One IMU message: orientation quaternion (x, y, z, w) and angular velocity, each None when absent."""

    stamp_ns: int
    frame_id: str
    orientation: tuple[float, float, float, float] | None
    angular_velocity: Vector | None


@dataclass(frozen=True, slots=True)
class DepthSample:
    """One depth message: the vehicle's z (m, up; 0 at the surface), None for a gap."""

    stamp_ns: int
    z: float | None


def _vector(v: Any) -> Vector:
    return (float(v.x), float(v.y), float(v.z))


def _finite(values: Iterable[float]) -> bool:
    return all(math.isfinite(v) for v in values)


def linear_covariance_diagonal(msg: Any, msgtype: str) -> tuple[float, float, float] | None:
    """Return the linear-velocity covariance diagonal of a DVL message, None for a type without covariance."""
    if msgtype == TWIST_TYPE:
        return None
    cov = np.asarray(msg.twist.covariance, dtype=float)
    return (float(cov[0]), float(cov[7]), float(cov[14]))


def dvl_sample(msg: Any, msgtype: str, stamp_ns: int, *, covariance_reported: bool) -> DvlSample:
    """Reduce a DVL message to a :class:`DvlSample` (lost-bottom rules in the module docstring).

    Args:
        msg: the deserialised message (one of :data:`DVL_TYPES`).
        msgtype: its type.
        stamp_ns: its stamp.
        covariance_reported: whether the topic's messages carry a covariance (:func:`reports_covariance`).
    """
    if msgtype == ODOMETRY_TYPE:
        frame, linear = str(msg.child_frame_id), _vector(msg.twist.twist.linear)
    elif msgtype == TWIST_COV_TYPE:
        frame, linear = str(msg.header.frame_id), _vector(msg.twist.twist.linear)
    else:
        frame, linear = str(msg.header.frame_id), _vector(msg.twist.linear)
    diagonal = linear_covariance_diagonal(msg, msgtype)
    lost = not _finite(linear)
    if diagonal is not None:
        lost = lost or diagonal[0] == -1.0 or (covariance_reported and all(d == 0.0 for d in diagonal))
    return DvlSample(stamp_ns, frame, None if lost else linear)


def reports_covariance(diagonals: Iterable[tuple[float, float, float] | None]) -> bool:
    """Return True when some DVL message carries a non-zero, finite linear covariance diagonal."""
    return any(d is not None and _finite(d) and any(v > 0.0 for v in d) for d in diagonals)


def imu_sample(msg: Any, stamp_ns: int) -> ImuSample:
    """Reduce a ``sensor_msgs/Imu`` to an :class:`ImuSample` (absent parts in the module docstring)."""
    q = (float(msg.orientation.x), float(msg.orientation.y), float(msg.orientation.z), float(msg.orientation.w))
    has_q = float(msg.orientation_covariance[0]) != -1.0 and _finite(q) and any(v != 0.0 for v in q)
    w = _vector(msg.angular_velocity)
    has_w = float(msg.angular_velocity_covariance[0]) != -1.0 and _finite(w)
    return ImuSample(stamp_ns, str(msg.header.frame_id), q if has_q else None, w if has_w else None)


def depth_from_pressure(pressure_pa: float, params: NavParams) -> float:
    """Return the depth (m, positive down) of an absolute pressure: ``(p − p₀) / (ρ·g)``."""
    return (pressure_pa - params.atmospheric_pa) / (params.water_density * params.gravity)


def depth_sample(msg: Any, msgtype: str, stamp_ns: int, params: NavParams) -> DepthSample:
    """Reduce a ``FluidPressure`` or ``PoseWithCovarianceStamped`` to a :class:`DepthSample`."""
    if msgtype == PRESSURE_TYPE:
        z = -depth_from_pressure(float(msg.fluid_pressure), params)
    else:
        z = float(msg.pose.pose.position.z)
    return DepthSample(stamp_ns, z if math.isfinite(z) else None)


# -- mounting --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Mount:
    """A sensor's pose in the body frame: ``v_body = rotation · v_sensor``, ``translation`` its lever arm (m)."""

    rotation: FloatArray = field(default_factory=lambda: np.eye(3))
    translation: FloatArray = field(default_factory=lambda: np.zeros(3))
    source: str = "parameters"


def rpy_matrix(roll_deg: float, pitch_deg: float, yaw_deg: float) -> FloatArray:
    """Return ``Rz(yaw)·Ry(pitch)·Rx(roll)`` (REP 103 fixed-axis roll, pitch, yaw)."""
    r, p, y = (math.radians(v) for v in (roll_deg, pitch_deg, yaw_deg))
    rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    return np.asarray(rz @ ry @ rx, dtype=np.float64)


StaticTree = dict[str, tuple[str, FloatArray, FloatArray]]
"""child frame → (parent frame, rotation parent ← child, child origin in the parent)."""


def static_tree(messages: Iterable[Any]) -> StaticTree:
    """Collect the transforms of ``tf2_msgs/TFMessage`` messages (a later one for the same child wins)."""
    tree: StaticTree = {}
    for msg in messages:
        for tf in msg.transforms:
            rot = tf.transform.rotation
            rotation = quaternion_matrix(float(rot.x), float(rot.y), float(rot.z), float(rot.w))
            translation = np.array(_vector(tf.transform.translation))
            tree[str(tf.child_frame_id).lstrip("/")] = (str(tf.header.frame_id).lstrip("/"), rotation, translation)
    return tree


def mount_from_tree(tree: StaticTree, frame: str, body_frame: str) -> Mount | None:
    """Chain the static transforms from ``frame`` up to ``body_frame`` (or the tree's root); None when absent."""
    frame = frame.lstrip("/")
    if frame == body_frame.lstrip("/"):
        return Mount(source="body frame")
    if frame not in tree:
        return None
    rotation, translation = np.eye(3), np.zeros(3)
    current, seen = frame, set()
    while current in tree and current != body_frame and current not in seen:
        seen.add(current)
        parent, r, t = tree[current]
        rotation, translation = r @ rotation, r @ translation + t
        current = parent
    return Mount(rotation, translation, source=f"{TF_STATIC_TOPIC} ({frame} → {current})")


def sensor_mount(tree: StaticTree, frame: str, params: NavParams, sensor: str) -> Mount:
    """Return the sensor's mounting: from ``/tf_static`` when it holds ``frame``, else the parameters."""
    found = mount_from_tree(tree, frame, params.body_frame) if frame else None
    if found is not None:
        return found
    if sensor == "dvl":
        return Mount(rpy_matrix(*params.dvl_rpy_deg), np.asarray(params.dvl_xyz, dtype=float))
    return Mount(rpy_matrix(*params.imu_rpy_deg), np.zeros(3))

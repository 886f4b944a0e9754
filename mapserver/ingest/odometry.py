"""Odometry messages to per-frame :class:`~core.motion.Motion` (4-DoF body-frame displacement).

Every ``nav_msgs/Odometry`` message is reduced to an :class:`OdometryState`: the pose as position plus
heading (yaw of the body x axis projected on the horizontal plane), and the twist as forward, lateral and
vertical speed and yaw rate. The twist of ``nav_msgs/Odometry`` is given in the child (body) frame; when
the pose orientation is not the identity, the body velocity ``v`` and rate ``ω`` are rotated into the
odometry frame with it (``R·v``, ``R·ω``), forward/lateral speed are the projections of ``R·v`` on the
horizontal heading direction and its left normal, vertical speed is its z component, and the yaw rate is
the z component of ``R·ω``. For a planar robot this is simply ``(v.x, v.y, v.z, ω.z)``.

Two ways to turn a stream of states into the motion between two frame stamps ``t0 < t1``:

* **twist** (:func:`integrate_twist`): zero-order hold, each message's velocity holds from its stamp until
  the next message's stamp (before the first message the robot is at rest; after the last its velocity
  keeps holding). The piecewise-constant velocities are integrated exactly over ``[t0, t1]`` (circular arcs
  for constant speed and yaw rate, with the ω → 0 limit), composing the SE(2)+z increments. The result does
  not depend on where the messages fall relative to the frames. ``dyaw`` is the integrated heading change
  (not wrapped).
* **pose** (:func:`difference_poses`): for logs whose twist is zero. The pose is interpolated at each
  frame stamp (position linearly, yaw linearly along the shorter way round; held constant before the first
  and after the last message) and the displacement is expressed in the previous frame's heading frame;
  ``dyaw`` is wrapped to (-π, π].

:class:`OdometryTrack` holds the states between two frames for streaming use; everything else is a pure
function.

Validation (:class:`OdometryCheck`, on the way from the log to the engine; the bounds are those of
:mod:`mapserver.bounds`, imported here under the same names):

* an odometry message is **dropped** when a value of its state is not finite (NaN, ±inf), a position
  coordinate is beyond :data:`MAX_POSITION_M` (1e8 m), its speed (the norm of forward, lateral and vertical)
  is above :data:`MAX_SPEED_M_S` (1000 m/s) or its yaw rate is above :data:`MAX_YAW_RATE_RAD_S` (100 rad/s).
  The motion across it then comes from its neighbours (the previous twist held; the poses on either side
  interpolated);
* a frame's motion is **dropped** (zero displacement and heading change over the frame's ``dt``) when a value
  is not finite or it moves faster than :data:`MAX_SPEED_M_S` over ``dt`` (a jump of the poses, or of the
  stamps);
* the log is **refused** (:class:`~mapserver.errors.IngestError`) as soon as the dropped messages are more
  than :data:`MAX_BAD_FRACTION` (5 %) of the odometry topic's messages, or the dropped frame motions more
  than 5 % of the log's frames.

The counts, by reason, are the run's :class:`~mapserver.ingest.frames.IngestReport`.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from core.angles import wrap_angle_exact
from core.motion import Motion
from core.se3 import compose_step, relative_step
from mapserver.bounds import MAX_BAD_FRACTION, MAX_POSITION_M, MAX_SPEED_M_S, MAX_YAW_RATE_RAD_S
from mapserver.errors import IngestError
from mapserver.ingest.frames import IngestReport

OdometryMode = Literal["twist", "pose"]
NS = 1e-9
_SMALL_ANGLE = 1e-4
POSE_EPSILON = 1e-9  # metres / radians: a pose change above this counts as motion (mode detection)
_SLACK_M = 1e-6  # rounding allowed on a frame's displacement bound

Increment = tuple[float, float, float, float]
Pose4 = tuple[float, float, float, float]


@dataclass(frozen=True, slots=True)
class OdometryState:
    """One odometry message reduced to 4 DoF.

    Attributes:
        stamp_ns: header stamp in nanoseconds.
        x: position x in the odometry frame (m).
        y: position y (m).
        z: position z (m).
        yaw: heading (rad).
        forward: forward speed along the horizontal heading (m/s).
        lateral: leftward speed (m/s).
        vertical: upward speed (m/s).
        yaw_rate: heading rate (rad/s).

    """

    stamp_ns: int
    x: float
    y: float
    z: float
    yaw: float
    forward: float = 0.0
    lateral: float = 0.0
    vertical: float = 0.0
    yaw_rate: float = 0.0

    @property
    def pose(self) -> Pose4:
        """Return ``(x, y, z, yaw)``."""
        return (self.x, self.y, self.z, self.yaw)


def quaternion_matrix(qx: float, qy: float, qz: float, qw: float) -> npt.NDArray[np.float64]:
    """Return the rotation matrix of a quaternion (normalised; a zero quaternion gives the identity)."""
    norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if norm < 1e-12:
        return np.eye(3)
    x, y, z, w = qx / norm, qy / norm, qz / norm, qw / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def yaw_of_matrix(rotation: npt.NDArray[np.float64]) -> float:
    """Return the heading of the body x axis projected on the horizontal plane."""
    return math.atan2(float(rotation[1, 0]), float(rotation[0, 0]))


def make_state(
    stamp_ns: int,
    position: Sequence[float],
    orientation: Sequence[float],
    linear: Sequence[float] = (0.0, 0.0, 0.0),
    angular: Sequence[float] = (0.0, 0.0, 0.0),
) -> OdometryState:
    """Reduce a pose and a body-frame twist to an :class:`OdometryState`.

    Args:
        stamp_ns: stamp in nanoseconds.
        position: (x, y, z) in the odometry frame.
        orientation: quaternion (qx, qy, qz, qw) of the body in the odometry frame.
        linear: body-frame linear velocity (m/s).
        angular: body-frame angular velocity (rad/s).

    Returns:
        The state (see the module docstring for the projection).

    """
    with np.errstate(invalid="ignore", over="ignore"):  # a non-finite message gives a state that is dropped
        rotation = quaternion_matrix(*orientation)
        yaw = yaw_of_matrix(rotation)
        v_world = rotation @ np.asarray(linear, dtype=float)
        w_world = rotation @ np.asarray(angular, dtype=float)
        c, s = math.cos(yaw), math.sin(yaw)
        return OdometryState(
            stamp_ns=int(stamp_ns),
            x=float(position[0]),
            y=float(position[1]),
            z=float(position[2]),
            yaw=yaw,
            forward=float(c * v_world[0] + s * v_world[1]),
            lateral=float(-s * v_world[0] + c * v_world[1]),
            vertical=float(v_world[2]),
            yaw_rate=float(w_world[2]),
        )


def state_from_message(msg: Any, stamp_ns: int) -> OdometryState:
    """Reduce a deserialised ``nav_msgs/msg/Odometry`` to an :class:`OdometryState`."""
    pose = msg.pose.pose
    twist = msg.twist.twist
    return make_state(
        stamp_ns,
        (pose.position.x, pose.position.y, pose.position.z),
        (pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w),
        (twist.linear.x, twist.linear.y, twist.linear.z),
        (twist.angular.x, twist.angular.y, twist.angular.z),
    )


def twist_is_zero(msg: Any) -> bool:
    """Return True when an ``Odometry`` message carries no twist: all six components exactly zero.

    A twist with a non-finite component, or one beyond the bounds (the message would be dropped), carries
    none either.
    """
    twist = msg.twist.twist
    values = (
        twist.linear.x,
        twist.linear.y,
        twist.linear.z,
        twist.angular.x,
        twist.angular.y,
        twist.angular.z,
    )
    if all(v == 0.0 for v in values):
        return True
    finite = all(math.isfinite(float(v)) for v in values)
    return not finite or math.hypot(*values[:3]) > MAX_SPEED_M_S or abs(float(values[5])) > MAX_YAW_RATE_RAD_S


def state_problem(state: OdometryState) -> str | None:
    """Return why ``state`` must be dropped (see the module docstring), None when it is usable."""
    values = (state.x, state.y, state.z, state.yaw, state.forward, state.lateral, state.vertical, state.yaw_rate)
    if not all(math.isfinite(v) for v in values):
        return "non-finite value"
    if max(abs(state.x), abs(state.y), abs(state.z)) > MAX_POSITION_M:
        return f"position beyond {MAX_POSITION_M:g} m"
    if math.hypot(state.forward, state.lateral, state.vertical) > MAX_SPEED_M_S:
        return f"speed above {MAX_SPEED_M_S:g} m/s"
    if abs(state.yaw_rate) > MAX_YAW_RATE_RAD_S:
        return f"yaw rate above {MAX_YAW_RATE_RAD_S:g} rad/s"
    return None


def motion_problem(motion: Motion) -> str | None:
    """Return why a frame's ``motion`` must be dropped (see the module docstring), None when it is usable."""
    if not all(math.isfinite(v) for v in (motion.dx, motion.dy, motion.dz, motion.dyaw, motion.dt)):
        return "non-finite value"
    if math.hypot(motion.dx, motion.dy, motion.dz) > MAX_SPEED_M_S * max(motion.dt, 0.0) + _SLACK_M:
        return f"faster than {MAX_SPEED_M_S:g} m/s"
    return None


def pose_moved(a: OdometryState, b: OdometryState, epsilon: float = POSE_EPSILON) -> bool:
    """Return True when two usable states' poses differ by more than ``epsilon`` (m or rad)."""
    if state_problem(a) is not None or state_problem(b) is not None:
        return False
    return (
        abs(a.x - b.x) > epsilon
        or abs(a.y - b.y) > epsilon
        or abs(a.z - b.z) > epsilon
        or abs(wrap_angle_exact(a.yaw - b.yaw)) > epsilon
    )


def arc_increment(forward: float, lateral: float, vertical: float, yaw_rate: float, tau: float) -> Increment:
    """Exact displacement after ``tau`` seconds at constant body speeds and yaw rate.

    The body velocity ``(forward, lateral)`` is constant in the rotating body frame, so the displacement in
    the start frame is ``∫₀^τ R(ωs)·(v, u) ds`` = ``(A·v − B·u, B·v + A·u)`` with ``A = sin(ωτ)/ω`` and
    ``B = (1 − cos ωτ)/ω`` (limits ``τ`` and ``ωτ²/2`` as ω → 0).

    Args:
        forward: forward speed v (m/s).
        lateral: leftward speed u (m/s).
        vertical: upward speed (m/s).
        yaw_rate: ω (rad/s).
        tau: duration (s).

    Returns:
        ``(dx, dy, dz, dyaw)`` in the start frame.

    """
    theta = yaw_rate * tau
    if abs(theta) < _SMALL_ANGLE:
        t2 = theta * theta
        a = tau * (1.0 - t2 / 6.0 + t2 * t2 / 120.0)
        b = tau * theta * (0.5 - t2 / 24.0 + t2 * t2 / 720.0)
    else:
        a = math.sin(theta) / yaw_rate
        b = 2.0 * math.sin(theta / 2.0) ** 2 / yaw_rate
    return (a * forward - b * lateral, b * forward + a * lateral, vertical * tau, theta)


def integrate_twist(states: Sequence[OdometryState], t0_ns: int, t1_ns: int) -> Motion:
    """Integrate zero-order-hold twist from ``t0_ns`` to ``t1_ns`` (see the module docstring).

    Args:
        states: odometry states sorted by stamp; the one active at ``t0_ns`` (the last with a stamp at or
            before it) must be included when it exists.
        t0_ns: previous frame stamp.
        t1_ns: current frame stamp.

    Returns:
        The motion in the frame at ``t0_ns``; zero with ``dt = 0`` when ``t1_ns <= t0_ns``.

    """
    if t1_ns <= t0_ns:
        return Motion(0.0, 0.0, 0.0, 0.0, 0.0)
    stamps = [s.stamp_ns for s in states]
    index = bisect_right(stamps, t0_ns) - 1  # active state at t0 (-1: none yet, at rest)
    total: Increment = (0.0, 0.0, 0.0, 0.0)
    start = t0_ns
    while start < t1_ns:
        nxt = index + 1
        end = min(stamps[nxt], t1_ns) if nxt < len(stamps) else t1_ns
        if index >= 0:
            st = states[index]
            step = arc_increment(st.forward, st.lateral, st.vertical, st.yaw_rate, (end - start) * NS)
            total = compose_step(total, step)  # the heading summed, not wrapped
        start = end
        index = nxt if nxt < len(stamps) and stamps[nxt] <= start else index
    return Motion(total[0], total[1], total[2], total[3], (t1_ns - t0_ns) * NS)


def interpolate_pose(states: Sequence[OdometryState], t_ns: int) -> Pose4:
    """Interpolate the pose at ``t_ns`` (held constant outside the states' span).

    Args:
        states: at least one odometry state, sorted by stamp.
        t_ns: the stamp.

    Returns:
        ``(x, y, z, yaw)``: position linear, yaw linear along the shorter way round (wrapped).

    """
    if not states:
        msg = "interpolate_pose needs at least one state"
        raise ValueError(msg)
    stamps = [s.stamp_ns for s in states]
    hi = bisect_right(stamps, t_ns)
    if hi == 0:
        return states[0].pose
    if hi == len(states):
        return states[-1].pose
    a, b = states[hi - 1], states[hi]
    if a.stamp_ns == t_ns:
        return a.pose
    alpha = (t_ns - a.stamp_ns) / (b.stamp_ns - a.stamp_ns)
    return (
        a.x + alpha * (b.x - a.x),
        a.y + alpha * (b.y - a.y),
        a.z + alpha * (b.z - a.z),
        wrap_angle_exact(a.yaw + alpha * wrap_angle_exact(b.yaw - a.yaw)),
    )


def relative_motion(start: Pose4, end: Pose4, dt: float) -> Motion:
    """Express the displacement from ``start`` to ``end`` in ``start``'s heading frame.

    Args:
        start: ``(x, y, z, yaw)`` of the previous frame.
        end: ``(x, y, z, yaw)`` of the current frame.
        dt: elapsed seconds.

    Returns:
        The motion, ``dyaw`` wrapped to (-π, π].

    """
    dx, dy, dz, dyaw = relative_step(start, end)
    return Motion(dx, dy, dz, wrap_angle_exact(dyaw), dt)


def difference_poses(states: Sequence[OdometryState], t0_ns: int, t1_ns: int) -> Motion:
    """Motion from ``t0_ns`` to ``t1_ns`` by differencing interpolated poses.

    Args:
        states: odometry states sorted by stamp, bracketing both stamps where the log allows.
        t0_ns: previous frame stamp.
        t1_ns: current frame stamp.

    Returns:
        The motion; zero when ``t1_ns <= t0_ns`` or there are no states.

    """
    if t1_ns <= t0_ns or not states:
        return Motion(0.0, 0.0, 0.0, 0.0, max(0, t1_ns - t0_ns) * NS)
    return relative_motion(
        interpolate_pose(states, t0_ns), interpolate_pose(states, t1_ns), (t1_ns - t0_ns) * NS
    )


def frame_motion(mode: OdometryMode, states: Sequence[OdometryState], t0_ns: int, t1_ns: int) -> Motion:
    """Dispatch to :func:`integrate_twist` or :func:`difference_poses`."""
    if mode == "twist":
        return integrate_twist(states, t0_ns, t1_ns)
    return difference_poses(states, t0_ns, t1_ns)


class OdometryCheck:
    """Drops unusable odometry messages and frame motions, counts them, refuses a log with too many.

    Args:
        messages: the odometry topic's message count (the base of the message fraction).
        frames: the log's frame count (the base of the frame-motion fraction).
        source: what the refusal's message names (the log).
    """

    def __init__(self, *, messages: int, frames: int, source: str = "") -> None:
        self.messages = messages
        self.frames = frames
        self.source = source
        self.report = IngestReport()

    def accept(self, state: OdometryState) -> bool:
        """Return whether ``state`` is usable; count it as dropped otherwise.

        Raises:
            IngestError: the dropped messages are now more than ``MAX_BAD_FRACTION`` of the topic's.
        """
        self.report.odometry_messages += 1
        problem = state_problem(state)
        if problem is None:
            return True
        dropped = self.report.dropped_messages
        dropped[problem] = dropped.get(problem, 0) + 1
        self._refuse_past(dropped, max(self.messages, self.report.odometry_messages), "odometry messages")
        return False

    def motion(self, motion: Motion) -> Motion:
        """Return a frame's ``motion``, or zero displacement over its ``dt`` when it is dropped (counted).

        Raises:
            IngestError: the dropped frame motions are now more than ``MAX_BAD_FRACTION`` of the frames.
        """
        self.report.frames += 1
        problem = motion_problem(motion)
        if problem is None:
            return motion
        dropped = self.report.dropped_motions
        dropped[problem] = dropped.get(problem, 0) + 1
        self._refuse_past(dropped, max(self.frames, self.report.frames), "frames' motions")
        dt = motion.dt if math.isfinite(motion.dt) else 0.0
        return Motion(0.0, 0.0, 0.0, 0.0, dt)

    def _refuse_past(self, dropped: dict[str, int], total: int, what: str) -> None:
        bad = sum(dropped.values())
        if bad > MAX_BAD_FRACTION * total:
            reasons = ", ".join(f"{reason}: {count}" for reason, count in dropped.items())
            msg = (
                f"{self.source}: unusable odometry: {bad} of the log's {total} {what} dropped ({reasons}); a log "
                f"is refused when more than {MAX_BAD_FRACTION:.0%} are"
            )
            raise IngestError(msg)


class OdometryTrack:
    """A bounded buffer of odometry states for streaming frame-by-frame integration.

    Push states in stamp order (a state older than the newest one is dropped: header stamps must not go
    backwards within a topic); ask :meth:`motion` once :meth:`covers` the frame stamp or the stream has
    ended; :meth:`motion` then drops the states no later interval can need, so memory stays bounded by the
    odometry between two frames. With a ``check``, unusable states are dropped on :meth:`push` and every
    motion goes through :meth:`OdometryCheck.motion`.
    """

    def __init__(self, mode: OdometryMode, check: OdometryCheck | None = None) -> None:
        self.mode: OdometryMode = mode
        self.check = check
        self.states: list[OdometryState] = []
        self.dropped = 0

    def push(self, state: OdometryState) -> None:
        """Append a state (dropped when unusable, or when its stamp is older than the newest state's)."""
        if self.check is not None and not self.check.accept(state):
            return
        if self.states and state.stamp_ns < self.states[-1].stamp_ns:
            self.dropped += 1
            return
        self.states.append(state)

    def covers(self, t_ns: int) -> bool:
        """Return True when a state strictly after ``t_ns`` has been pushed (nothing later can matter)."""
        return bool(self.states) and self.states[-1].stamp_ns > t_ns

    def motion(self, t0_ns: int, t1_ns: int) -> Motion:
        """Return the motion from ``t0_ns`` to ``t1_ns``; forget the states no later interval needs."""
        result = frame_motion(self.mode, self.states, t0_ns, t1_ns)
        self.trim(max(t0_ns, t1_ns))
        return result if self.check is None else self.check.motion(result)

    def trim(self, t_ns: int) -> None:
        """Drop the states before the last one at or before ``t_ns``."""
        stamps = [s.stamp_ns for s in self.states]
        keep_from = bisect_right(stamps, t_ns) - 1
        if keep_from > 0:
            del self.states[:keep_from]

"""The vehicle's sensors as a plan's knobs: a forward camera, message rates, speed, JPEG, lighting, odometry errors.

The ground scenarios are rendered by default for the ``circle`` preset (a 360° camera at 1 Hz, 10 Hz odometry,
0.5 m/s). :func:`fit_sensors` re-equips any plan with other sensors — what the generalisation bench varies
per seed and what the ``street`` scenario uses — without changing its world or routes:

* a camera of ``fov_deg`` (square pixels, so the vertical field follows from the image size), mounted
  ``mount_height`` metres up, seeing ``max_range`` metres through a fog of ``fog_length``;
* camera and odometry rates; the nominal speed of every session (the lap boundaries in scenario.json follow);
* frames written as JPEG of a given quality (or raw ``mono8`` when ``jpeg_quality`` is 0);
* a light that changes between laps: the sun's direction turns by ``light_turn_deg`` and the exposure changes
  by the fraction ``light_gain`` per lap of the first session's route (:class:`~.render.Lighting`);
* the vehicle's odometry errors: speed scale error and yaw-rate bias magnitudes (signs are drawn per seed,
  :class:`~.drive.VehicleErrors`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from mapserver.ingest.simulator.render import Camera, Lighting
from mapserver.ingest.simulator.scenarios import Plan, SessionPlan


@dataclass(frozen=True)
class Sensors:
    """A forward-camera vehicle (see the module docstring for each field's meaning)."""

    fov_deg: float = 75.0
    width: int = 160
    height: int = 120
    mount_height: float = 1.5
    max_range: float = 30.0
    fog_length: float = 40.0
    blur_px: float = 0.7
    camera_hz: float = 10.0
    odom_hz: float = 20.0
    speed: float = 1.0
    jpeg_quality: int = 80
    light_turn_deg: float = 0.0
    light_gain: float = 0.0
    scale_error: float | None = None
    yaw_bias: float | None = None

    def camera(self) -> Camera:
        """Return the camera model (square pixels; blur as a small camera's optics)."""
        return Camera(
            width=self.width, height=self.height, hfov_deg=self.fov_deg, vfov_deg=None,
            mount_height=self.mount_height, fog_length=self.fog_length, max_range=self.max_range,
            fade=min(3.0, self.max_range / 4.0), fog_level=0.6, blur_px=self.blur_px, vblur_px=self.blur_px,
        )  # fmt: skip


def _lap_info(session: SessionPlan, speed: float) -> dict[str, object]:
    """Return the session's scenario.json info with its nominal lap times at ``speed``."""
    info = dict(session.info)
    if "nominal_lap_s" in info:
        laps = session.spec.distance_m / session.spec.route.length
        turn_s = abs(math.radians(session.spec.turn_deg)) / session.spec.turn_rate
        lap_s = session.spec.route.length / speed
        info["nominal_lap_s"] = [round(turn_s + k * lap_s, 3) for k in range(1, int(laps) + 1)]
    return info


def fit_sensors(plan: Plan, sensors: Sensors) -> Plan:
    """Return ``plan`` with the vehicle's sensors replaced by ``sensors`` (world and routes unchanged).

    Raises:
        ValueError: a rate, speed, size or quality out of range.
    """
    if not (sensors.camera_hz > 0 and sensors.odom_hz > 0 and sensors.speed > 0 and 0 < sensors.fov_deg < 360):
        msg = f"rates, speed and field of view must be positive (fov < 360°), got {sensors!r}"
        raise ValueError(msg)
    if not 0 <= sensors.jpeg_quality <= 100:
        msg = f"jpeg_quality must be 0 (raw frames) or 1..100, got {sensors.jpeg_quality!r}"
        raise ValueError(msg)

    def refit(session: SessionPlan) -> SessionPlan:
        spec = dataclasses.replace(session.spec, speed=sensors.speed)
        return dataclasses.replace(session, spec=spec, info=_lap_info(session, sensors.speed))

    sessions = tuple(refit(s) for s in plan.sessions)
    single = None
    if plan.single is not None:
        index = next((i for i, s in enumerate(plan.sessions) if s is plan.single), None)
        single = sessions[index] if index is not None else refit(plan.single)
    first = (plan.single or plan.sessions[0]).spec
    lap_s = first.route.length / sensors.speed
    lighting = None
    if sensors.light_turn_deg or sensors.light_gain:
        lighting = Lighting(math.radians(sensors.light_turn_deg) / lap_s, sensors.light_gain / lap_s)
    noise = plan.noise
    if sensors.scale_error is not None:
        noise = dataclasses.replace(noise, scale_error=sensors.scale_error)
    if sensors.yaw_bias is not None:
        noise = dataclasses.replace(noise, yaw_bias=sensors.yaw_bias)
    return dataclasses.replace(
        plan,
        camera=sensors.camera(),
        rates=dataclasses.replace(plan.rates, camera_hz=sensors.camera_hz, odom_hz=sensors.odom_hz),
        noise=noise,
        sessions=sessions,
        single=single,
        image_encoding="jpeg" if sensors.jpeg_quality else "mono8",
        jpeg_quality=sensors.jpeg_quality or 95,
        lighting=lighting,
    )

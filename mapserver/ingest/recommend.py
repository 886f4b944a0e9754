"""The preset and the settings a log decides (``mapserver inspect``'s recommendation).

From the survey (:mod:`mapserver.ingest.survey`) and the camera (:mod:`mapserver.ingest.camera`):

* **field of view**: ``--fov DEG`` when given, else a ``CameraInfo`` topic's, else unknown — then ``needs``
  holds ``"fov"`` and a note names the flag and the key to pass (``inspect --fov DEG``, ``process --set
  camera_fov_deg=DEG``);
* **panoramic**: a field of view of 360°; with the field unknown, an image at least :data:`PANORAMIC_ASPECT`
  times as wide as high (a 360° strip: the Virtual Tour's 256 × 64; forward cameras are 4:3 to 16:9);
* **preset**: ``circle`` for a panoramic camera (the simulator's 360° ground scenarios), ``forward`` otherwise
  (the generalisation bench's forward-camera logs);
* **settings** on top of the preset: ``camera_fov_deg`` (when known; 360 for a panorama), ``camera_hz`` (the
  image topic's rate), ``template_x_size``/``template_y_size`` (the preset's, no larger than the image),
  ``vt_panoramic`` (the preset's: ``circle`` matches its panoramas without wrapping, measured in
  docs/journal.md), and for ``circle`` on an image other than 256 × 64 the visual-odometry windows as the whole
  image (``-1``);
* **rates**: the camera's and the odometry's mean rate (Hz), for the user to check against the robot's.

The settings are printed as a ``--set`` argument and as an OpenRatSLAM INI (``--config``) that holds every
key where preset and settings differ from the defaults, so either gives the same parameters.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from core import Params, preset
from mapserver.ingest.camera import CameraGeometry
from mapserver.ingest.survey import LogSurvey

PANORAMIC_ASPECT = 3.0
"""Width over height from which an image of unknown field of view is taken for a 360° panorama."""
FULL_TURN_DEG = 360.0
VIRTUAL_TOUR_IMAGE = (256, 64)
"""The image ``circle``'s visual-odometry windows (0..256 × 0..64) cover whole."""
_WINDOW_KEYS = ("vtrans_image_x_max", "vtrans_image_y_max", "vrot_image_x_max", "vrot_image_y_max")
NEED_TEXTS = {
    "fov": "field of view unknown (no CameraInfo topic): give the camera's horizontal field of view, "
    "'inspect LOG --fov DEG' or 'process LOG --set camera_fov_deg=DEG' (until then the preset's)",
}
"""What the user must give, by the ``needs`` key: the notes that say so."""


@dataclass
class Recommendation:
    """A preset, the settings on top of it, and what the log could not say."""

    preset: str
    settings: dict[str, Any]
    camera: dict[str, Any]
    needs: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def params(self) -> Params:
        """Return the recommended parameters: the preset with the settings."""
        return preset(self.preset).replace(**self.settings)

    def set_argument(self) -> str:
        """Return the settings as ``process``'s ``--set`` value (``key=value,...``)."""
        return ",".join(f"{key}={_text(value)}" for key, value in self.settings.items())

    def ini(self) -> str:
        """Return an OpenRatSLAM INI holding every key where the recommended parameters differ from the defaults."""
        chosen, defaults = self.params(), Params()
        lines = ["[ratslam]"]
        for f in dataclasses.fields(Params):
            value = getattr(chosen, f.name)
            if value != getattr(defaults, f.name):
                lines.append(f"{f.name} = {_text(value)}".rstrip())
        return "\n".join(lines) + "\n"

    def as_dict(self) -> dict[str, Any]:
        """Return the ``inspect --json`` ``recommendation`` object."""
        return {
            "preset": self.preset,
            "settings": dict(self.settings),
            "set": self.set_argument(),
            "ini": self.ini(),
            "camera": dict(self.camera),
            "needs": list(self.needs),
            "notes": list(self.notes),
        }


def _text(value: Any) -> str:
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return str(value)


def _panoramic(camera: CameraGeometry, fov: float | None) -> tuple[bool, str]:
    """Return whether the camera sees the full turn, and what says so (``fov`` or ``aspect``)."""
    if fov is not None:
        return fov >= FULL_TURN_DEG, "fov"
    return camera.width >= PANORAMIC_ASPECT * camera.height, "aspect"


def _settings(name: str, camera: CameraGeometry, fov: float | None, camera_hz: float | None) -> dict[str, Any]:
    """Return the keys the log decides on top of preset ``name`` (module docstring)."""
    base = preset(name)
    out: dict[str, Any] = {}
    if fov is not None:
        out["camera_fov_deg"] = round(fov, 2)
    if camera_hz:
        out["camera_hz"] = round(camera_hz, 2)
    out["template_x_size"] = min(base.template_x_size, camera.width)
    out["template_y_size"] = min(base.template_y_size, camera.height)
    out["vt_panoramic"] = base.vt_panoramic
    if name == "circle" and (camera.width, camera.height) != VIRTUAL_TOUR_IMAGE:
        out.update(dict.fromkeys(_WINDOW_KEYS, -1))
    return out


def recommend(survey: LogSurvey, fov_deg: float | None = None) -> Recommendation | None:
    """Return the preset and settings for a usable log (module docstring); None when ``process`` cannot read it.

    ``fov_deg``: the camera's horizontal field of view as the user gives it (``inspect --fov``); it wins over a
    ``CameraInfo`` topic's.
    """
    camera = survey.camera
    if not survey.usable or camera is None:
        return None
    fov, source = (fov_deg, "--fov") if fov_deg is not None else (camera.fov_deg, camera.fov_topic)
    panoramic, panoramic_from = _panoramic(camera, fov)
    name = "circle" if panoramic else "forward"
    if fov is None and panoramic:
        fov, source = FULL_TURN_DEG, "aspect"
    camera_hz, odometry_hz = survey.rate_hz("image"), survey.rate_hz("odometry")
    rec = Recommendation(
        preset=name,
        settings=_settings(name, camera, fov, camera_hz),
        camera={
            "width": camera.width, "height": camera.height, "fov_deg": fov, "fov_source": source,
            "panoramic": panoramic, "panoramic_from": panoramic_from, "camera_hz": camera_hz,
            "odometry_hz": odometry_hz,
        },
    )  # fmt: skip
    if fov is None:
        rec.needs.append("fov")
        rec.notes.append(NEED_TEXTS["fov"])
    if odometry_hz is None:
        rec.notes.append("no odometry topic: process runs visual odometry, which reads camera_fov_deg, camera_hz "
                         "and vtrans_scaling (metres per unit of image change)")
    elif camera_hz and odometry_hz < camera_hz:
        rec.notes.append(f"odometry ({odometry_hz:.1f} Hz) is slower than the camera ({camera_hz:.1f} Hz): "
                         "between two messages the motion is held (twist) or interpolated (pose)")
    return rec

"""Which topic of a mission log is the camera, the odometry and the ground truth.

Automatic mapping rule (``inspect`` shows its result, ``--topics`` overrides it); topics with no messages
are never chosen:

* **image**: among ``sensor_msgs/msg/Image`` and ``sensor_msgs/msg/CompressedImage`` topics, the one with
  the most messages; ties prefer a name containing ``camera`` or ``image``, then the alphabetically first.
  Topics whose name contains ``depth`` are considered only when no other image topic exists (a depth
  stream is not a camera for place recognition).
* **odometry**: among ``nav_msgs/msg/Odometry`` topics that are not *truth-like*, the one with the most
  messages (ties: alphabetical). A name is truth-like when it contains (case-insensitive) one of
  ``ground_truth``, ``groundtruth``, ``truth``, ``overhead``, ``mocap``, ``vicon``, or has ``gt`` as a
  token (the name split at ``/``, ``_``, ``-`` and ``.``; so ``/robot/gt/odom`` and ``/odom_gt`` are
  truth-like but ``/lengths`` is not).
* **ground_truth**: among truth-like ``Odometry``, ``PoseStamped`` and ``PoseWithCovarianceStamped``
  topics, the one with the most messages (ties: alphabetical); if there is none, the only
  ``PoseStamped``/``PoseWithCovarianceStamped`` topic when there is exactly one; otherwise none.

* **dvl**: among ``geometry_msgs/TwistWithCovarianceStamped`` and ``TwistStamped`` topics, the one with the
  most messages (ties prefer a name containing ``dvl``, then alphabetical); when there is none, the
  ``nav_msgs/Odometry`` topic whose name contains ``dvl`` with the most messages. An ``Odometry`` topic whose
  name contains ``dvl`` is never the ``odometry`` role.
* **imu**: the ``sensor_msgs/Imu`` topic with the most messages (ties prefer a name containing ``imu``).
* **depth**: the ``sensor_msgs/FluidPressure`` topic with the most messages (ties prefer a name containing
  ``depth`` or ``pressure``); when there is none, the ``PoseWithCovarianceStamped`` topic whose name contains
  ``depth``. A pose topic whose name contains ``depth`` is never the lone-pose ground truth.

  **Which motion the engine gets** (:func:`motion_source`): the ``odometry`` role when the log has one (a
  log with wheel or vehicle odometry keeps using it, whatever navigation sensors it also holds); otherwise
  the fusion of ``dvl`` and ``imu`` (and ``depth`` when mapped; :mod:`mapserver.ingest.fusion`) when both are
  mapped; otherwise none (visual odometry). ``--topics odometry=none`` makes a log with both use the fusion.

* **sonar**: never chosen automatically; ``--topics sonar=/topic`` names a ``sensor_msgs/Image`` or
  ``CompressedImage`` topic (not the camera's) whose images are the second modality of the ``sdr-htm``
  front-end (PoseidonSLAM Eq. 4.3).

Overrides (``--topics image=/a,odometry=/b``) name keys ``image``, ``odometry``, ``ground_truth``,
``sonar``, ``dvl``, ``imu`` and ``depth``; the value ``none`` (or an empty value) switches any of them but
``image`` off. An unknown key, a topic missing from the log or a topic of the wrong type is an
:class:`~mapserver.errors.IngestError`.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from mapserver.errors import IngestError, InputError
from mapserver.pairs import parse_pairs

IMAGE_TYPES = frozenset({"sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"})
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
POSE_TYPES = frozenset({"geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped"})
GROUND_TRUTH_TYPES = POSE_TYPES | {ODOMETRY_TYPE}
TWIST_TYPES = frozenset({"geometry_msgs/msg/TwistWithCovarianceStamped", "geometry_msgs/msg/TwistStamped"})
DVL_TYPES = TWIST_TYPES | {ODOMETRY_TYPE}
IMU_TYPES = frozenset({"sensor_msgs/msg/Imu"})
PRESSURE_TYPE = "sensor_msgs/msg/FluidPressure"
DEPTH_TYPES = frozenset({PRESSURE_TYPE, "geometry_msgs/msg/PoseWithCovarianceStamped"})
NAV_KEYS = ("dvl", "imu", "depth")
TOPIC_KEYS = ("image", "odometry", "ground_truth", "sonar", *NAV_KEYS)
TRUTH_WORDS = ("ground_truth", "groundtruth", "truth", "overhead", "mocap", "vicon")
TRUTH_TOKENS = ("gt",)
_OFF_VALUES = frozenset({"", "none"})
NO_CAMERA = "no camera topic: process needs sensor_msgs/Image or CompressedImage"


@dataclass(frozen=True, slots=True)
class TopicInfo:
    """One topic of a log.

    Attributes:
        name: topic name, e.g. ``/robot/camera/image``.
        msgtype: ROS 2 style message type, e.g. ``sensor_msgs/msg/Image`` (also for ROS 1 logs).
        count: number of messages.
        rate_hz: mean rate over the whole log, ``(count - 1) / duration`` (0 when undefined).

    """

    name: str
    msgtype: str
    count: int
    rate_hz: float


@dataclass(frozen=True, slots=True)
class TopicMapping:
    """The topics a log is read from.

    Attributes:
        image: camera topic (always present).
        odometry: odometry topic, or None (the engine then runs visual odometry).
        ground_truth: ground-truth pose topic, or None.
        sonar: second image topic (the sdr-htm front-end's sonar modality), or None.
        dvl: DVL velocity topic, or None.
        imu: IMU topic, or None.
        depth: pressure or depth topic, or None.

    """

    image: str
    odometry: str | None
    ground_truth: str | None
    sonar: str | None = None
    dvl: str | None = None
    imu: str | None = None
    depth: str | None = None

    @property
    def fused(self) -> bool:
        """True when the engine's motion is the DVL + IMU (+ depth) fusion (rule: :func:`motion_source`)."""
        return motion_source(self.as_dict()) == "navigation"

    def as_dict(self) -> dict[str, str | None]:
        """Return the mapping as ``{"image", "odometry", "ground_truth"}``, and ``"sonar"`` when there is one.

        (Without a sonar topic the dict is the one logs were identified by before the key existed.)
        """
        out = {"image": self.image, "odometry": self.odometry, "ground_truth": self.ground_truth}
        for key in ("sonar", *NAV_KEYS):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        return out


def motion_source(mapping: Mapping[str, str | None]) -> str | None:
    """Return ``odometry``, ``navigation`` (DVL + IMU fusion) or None (rule in the module docstring)."""
    if mapping.get("odometry"):
        return "odometry"
    if mapping.get("dvl") and mapping.get("imu"):
        return "navigation"
    return None


def is_truth_like(name: str) -> bool:
    """Return True when a topic name looks like ground truth (see the module docstring)."""
    lowered = name.lower()
    if any(word in lowered for word in TRUTH_WORDS):
        return True
    tokens = re.split(r"[/_\-.]", lowered)
    return any(token in TRUTH_TOKENS for token in tokens)


def _camera_like(name: str) -> bool:
    lowered = name.lower()
    return "camera" in lowered or "image" in lowered


def _pick_image(topics: Sequence[TopicInfo]) -> str | None:
    candidates = [t for t in topics if t.msgtype in IMAGE_TYPES and t.count > 0]
    if not candidates:
        return None
    non_depth = [t for t in candidates if "depth" not in t.name.lower()]
    pool = non_depth or candidates
    best = min(pool, key=lambda t: (-t.count, not _camera_like(t.name), t.name))
    return best.name


def _most(topics: Sequence[TopicInfo]) -> str | None:
    if not topics:
        return None
    return min(topics, key=lambda t: (-t.count, t.name)).name


def _named(name: str, *words: str) -> bool:
    lowered = name.lower()
    return any(word in lowered for word in words)


def _pick_odometry(topics: Sequence[TopicInfo]) -> str | None:
    return _most(
        [t for t in topics if t.msgtype == ODOMETRY_TYPE and t.count > 0 and not is_truth_like(t.name)
         and not _named(t.name, "dvl")]
    )


def _most_preferring(topics: Sequence[TopicInfo], *words: str) -> str | None:
    if not topics:
        return None
    return min(topics, key=lambda t: (-t.count, not _named(t.name, *words), t.name)).name


def _pick_navigation(topics: Sequence[TopicInfo]) -> dict[str, str | None]:
    """Return the ``dvl``, ``imu`` and ``depth`` roles (rule in the module docstring)."""
    live = [t for t in topics if t.count > 0 and not is_truth_like(t.name)]
    dvl = _most_preferring([t for t in live if t.msgtype in TWIST_TYPES], "dvl") or _most(
        [t for t in live if t.msgtype == ODOMETRY_TYPE and _named(t.name, "dvl")]
    )
    depth = _most_preferring([t for t in live if t.msgtype == PRESSURE_TYPE], "depth", "pressure") or _most(
        [t for t in live if t.msgtype in DEPTH_TYPES and _named(t.name, "depth")]
    )
    return {"dvl": dvl, "imu": _most_preferring([t for t in live if t.msgtype in IMU_TYPES], "imu"), "depth": depth}


def _pick_ground_truth(topics: Sequence[TopicInfo]) -> str | None:
    truth = [t for t in topics if t.msgtype in GROUND_TRUTH_TYPES and t.count > 0 and is_truth_like(t.name)]
    if truth:
        return _most(truth)
    poses = [t for t in topics if t.msgtype in POSE_TYPES and t.count > 0 and not _named(t.name, "depth")]
    if len(poses) == 1:
        return poses[0].name
    return None


def _override(
    key: str, value: str, by_name: Mapping[str, TopicInfo], allowed: frozenset[str], source: str
) -> str | None:
    if key != "image" and value.strip().lower() in _OFF_VALUES:
        return None
    info = by_name.get(value)
    if info is None:
        msg = f"{source}: topic {value!r} given for {key!r} is not in the log"
        raise IngestError(msg)
    if info.msgtype not in allowed:
        expected = ", ".join(sorted(allowed))
        msg = f"{source}: topic {value!r} given for {key!r} has type {info.msgtype!r}, expected {expected}"
        raise IngestError(msg)
    return value


def choose_topics(
    topics: Sequence[TopicInfo], overrides: Mapping[str, str] | None = None, *, source: str = "log"
) -> dict[str, str | None]:
    """Choose the image, odometry and ground-truth topics (rule in the module docstring); None = no such topic.

    Args:
        topics: the topics of the log.
        overrides: explicit choices, keys ``image``, ``odometry``, ``ground_truth``.
        source: the log's path, used in error messages.

    Returns:
        ``{"image", "odometry", "ground_truth"}``, each a topic name or None (``image`` None: no camera).

    Raises:
        IngestError: unknown key, or a topic not in the log or of the wrong type.

    """
    overrides = dict(overrides or {})
    unknown = sorted(set(overrides) - set(TOPIC_KEYS))
    if unknown:
        msg = f"{source}: unknown topic key {unknown[0]!r} (known: {', '.join(TOPIC_KEYS)})"
        raise IngestError(msg)
    by_name = {t.name: t for t in topics}
    allowed = {
        "image": IMAGE_TYPES,
        "odometry": frozenset({ODOMETRY_TYPE}),
        "ground_truth": GROUND_TRUTH_TYPES,
        "sonar": IMAGE_TYPES,
        "dvl": DVL_TYPES,
        "imu": IMU_TYPES,
        "depth": DEPTH_TYPES,
    }
    chosen: dict[str, str | None] = {
        "image": _pick_image(topics),
        "odometry": _pick_odometry(topics),
        "ground_truth": _pick_ground_truth(topics),
        "sonar": None,
        **_pick_navigation(topics),
    }
    for key, value in overrides.items():
        chosen[key] = _override(key, value, by_name, allowed[key], source)
    for key in ("sonar", *NAV_KEYS):
        if chosen[key] is None:
            del chosen[key]  # absent roles: the mapping reads as before the keys existed
    if overrides.get("dvl") and chosen.get("dvl") and not chosen.get("imu"):
        msg = f"{source}: the DVL topic {chosen['dvl']!r} needs an IMU topic (sensor_msgs/Imu) for the heading"
        raise IngestError(msg)
    if "sonar" in chosen and chosen["sonar"] == chosen["image"]:
        msg = f"{source}: the sonar topic {chosen['sonar']!r} is the camera topic: name another image topic"
        raise IngestError(msg)
    return chosen


def map_topics(
    topics: Sequence[TopicInfo], overrides: Mapping[str, str] | None = None, *, source: str = "log"
) -> TopicMapping:
    """Choose the topics ``process`` reads (:func:`choose_topics`), requiring a camera topic with messages.

    Raises:
        IngestError: unknown key, topic not in the log or of the wrong type, or no usable camera topic.

    """
    chosen = choose_topics(topics, overrides, source=source)
    image = chosen["image"]
    if image is None:
        msg = f"{source}: {NO_CAMERA} (none with messages in this log; 'mapserver inspect' lists its topics)"
        raise IngestError(msg)
    if next(t.count for t in topics if t.name == image) == 0:
        msg = f"{source}: camera topic {image!r} has no messages"
        raise IngestError(msg)
    return TopicMapping(image=image, odometry=chosen["odometry"], ground_truth=chosen["ground_truth"],
                        sonar=chosen.get("sonar"), dvl=chosen.get("dvl"), imu=chosen.get("imu"),
                        depth=chosen.get("depth"))


def parse_topics_arg(text: str) -> dict[str, str]:
    """Parse the ``--topics`` syntax ``image=/a,odometry=/b`` into a dict.

    Keys are not checked here (the log reader does that); values may be empty or ``none``.

    Args:
        text: comma-separated ``KEY=TOPIC`` pairs.

    Returns:
        ``{key: topic}``.

    Raises:
        InputError: a pair without ``=``, an empty key or a repeated key.

    """
    result = parse_pairs(text, flag="--topics", form="KEY=TOPIC", example="image=/camera/image")
    if not result:
        msg = f"bad --topics {text!r}: expected KEY=TOPIC[,KEY=TOPIC...]"
        raise InputError(msg)
    return result

"""What a mission log holds, whether or not ``process`` can use it (the ``inspect`` command's data).

:func:`survey_log` lists every topic of any readable log — type, message count, time span and rate — with
rosbags' storage readers (ROS 1 ``.bag``, ROS 2 bag directory, standalone ``.db3``/``.mcap``), which need
neither the message definitions nor a camera. Then it chooses the topic mapping with the rule of
:mod:`mapserver.ingest.topics` and, when a camera topic exists, opens the log the way ``process`` does
(:func:`~mapserver.ingest.reader.open_log`: message definitions parsed, first image decoded), so
``usable`` is True exactly when ``process`` can read the log.

* **Time span**: a topic's first and last bag (receive) time, in seconds after the log's first message;
  **rate** = (count − 1) / span (0 for fewer than two messages or a zero span).
* **Roles**: ``image`` is required; a log without it is listed, with ``missing = ["image"]`` and the
  reason (``no camera topic: process needs sensor_msgs/Image or CompressedImage``). ``odometry`` and
  ``ground_truth`` are optional (``process`` falls back to visual odometry; ``evaluate`` takes a TUM file);
  their absence is a note.
* **Motion** (``motion``): where the engine's motion comes from (:func:`~mapserver.ingest.topics.motion_source`):
  ``odometry``, ``navigation`` (the ``dvl``, ``imu`` and, when found, ``depth`` roles fused,
  :mod:`mapserver.ingest.fusion`) or None (visual odometry). The navigation roles are shown when found,
  whatever the motion source; a DVL without an IMU is noted as unused.
* A log ``process`` cannot open although its topics are readable (its first image does not decode, its
  message definitions do not parse) is listed with ``usable = False``, ``image`` missing and the reason.
* **Camera** (a usable log only): the first frame's size and, from a ``CameraInfo`` topic, the field of view
  (:mod:`mapserver.ingest.camera`).

Errors (:class:`~mapserver.errors.IngestError`): a missing path, a file that is not a log or whose storage
cannot be read, and a bad ``--topics`` override.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rosbags.rosbag1 import Reader as Reader1
from rosbags.rosbag2 import Reader as Reader2

from mapserver.errors import IngestError
from mapserver.ingest.camera import CameraGeometry, read_camera
from mapserver.ingest.reader import _check_path, _describe, open_log
from mapserver.ingest.topics import NO_CAMERA, TopicInfo, choose_topics, motion_source

REQUIRED_ROLES = ("image",)
ROLE_NEEDS = {
    "image": NO_CAMERA,
    "odometry": "no odometry topic: process will run visual odometry (it reads nav_msgs/Odometry)",
    "ground_truth": "no ground-truth topic (nav_msgs/Odometry, PoseStamped or PoseWithCovarianceStamped)",
}


@dataclass(frozen=True, slots=True)
class TopicSpan:
    """One topic: type, count and the bag times of its first and last message (ns; 0 when it has none)."""

    name: str
    msgtype: str
    count: int
    first_ns: int
    last_ns: int

    @property
    def span_s(self) -> float:
        """Seconds between the topic's first and last message."""
        return (self.last_ns - self.first_ns) * 1e-9 if self.count else 0.0

    @property
    def rate_hz(self) -> float:
        """Mean rate over the topic's own span: (count − 1) / span."""
        span = self.span_s
        return (self.count - 1) / span if self.count > 1 and span > 0 else 0.0


@dataclass
class LogSurvey:
    """A log's topics, the mapping ``process`` would use and what stops it (see the module docstring)."""

    path: Path
    topics: list[TopicSpan]
    mapping: dict[str, str | None]
    start_ns: int
    end_ns: int
    odometry_mode: str | None = None
    motion: str | None = None
    camera: CameraGeometry | None = None
    missing: list[str] = field(default_factory=list)
    reasons: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    @property
    def usable(self) -> bool:
        """True when ``process`` can read the log (a camera topic whose first image decodes)."""
        return not self.missing

    def frames(self) -> int:
        """Messages on the image topic (0 without one)."""
        image = self.mapping.get("image")
        return next((t.count for t in self.topics if t.name == image), 0)

    def rate_hz(self, role: str) -> float | None:
        """Mean rate of the topic mapped to ``role`` (``image``, ``odometry``, ...), None when none is mapped."""
        name = self.mapping.get(role)
        return next((t.rate_hz for t in self.topics if t.name == name), None) if name else None

    def as_dict(self) -> dict[str, Any]:
        """Return the ``inspect --json`` object (contract keys plus spans, reasons and notes)."""
        start = self.start_ns
        return {
            "log": str(self.path),
            "topics": [
                {
                    "name": t.name,
                    "type": t.msgtype,
                    "count": t.count,
                    "rate_hz": round(t.rate_hz, 3),
                    "first_s": round((t.first_ns - start) * 1e-9, 6) if t.count else None,
                    "last_s": round((t.last_ns - start) * 1e-9, 6) if t.count else None,
                    "span_s": round(t.span_s, 6),
                }
                for t in self.topics
            ],
            "mapping": dict(self.mapping),
            "odometry_mode": self.odometry_mode,
            "motion": self.motion,
            "frames": self.frames(),
            "start_time_s": start * 1e-9 if self.topics and any(t.count for t in self.topics) else None,
            "duration_s": round((self.end_ns - self.start_ns) * 1e-9, 6),
            "usable": self.usable,
            "missing": list(self.missing),
            "reasons": dict(self.reasons),
            "notes": list(self.notes),
        }


def _storage_reader(path: Path) -> Reader1 | Reader2:
    """Open the log's storage reader (no message definitions parsed)."""
    try:
        reader: Reader1 | Reader2 = Reader1(path) if path.suffix.lower() == ".bag" else Reader2(path)
        reader.open()
    except Exception as err:  # rosbags raises many types for broken files
        msg = f"not a readable bag (truncated or corrupt?): {str(path)!r}: {_describe(err)}"
        raise IngestError(msg) from err
    return reader


def _message_times(reader: Reader1 | Reader2) -> Iterator[tuple[str, int]]:
    """Yield (topic, bag time) of every message.

    A ROS 1 bag's index (read at open) gives them without touching message data; other logs are read.
    """
    indexes = getattr(reader, "indexes", None)
    if isinstance(reader, Reader1) and isinstance(indexes, dict):
        for conn in reader.connections:
            for entry in indexes.get(conn.id, ()):
                yield conn.topic, int(entry.time)
        return
    for conn, stamp, _raw in reader.messages():
        yield conn.topic, int(stamp)


def topic_spans(path: Path) -> list[TopicSpan]:
    """Return every topic of the log with its type, count and first/last bag time (ROS 1: from the index).

    A topic recorded over several connections (ROS 1 bags do this per publisher) is one row; its type is
    the connections' type, or the distinct types joined by ``|``.
    """
    reader = _storage_reader(path)
    try:
        types: dict[str, set[str]] = {}
        counts: dict[str, int] = {}
        first: dict[str, int] = {}
        last: dict[str, int] = {}
        for conn in reader.connections:
            types.setdefault(conn.topic, set()).add(str(conn.msgtype or ""))
            counts.setdefault(conn.topic, 0)
        for topic, stamp in _message_times(reader):
            counts[topic] += 1
            first[topic] = min(first.get(topic, stamp), stamp)
            last[topic] = max(last.get(topic, stamp), stamp)
    except IngestError:
        raise
    except Exception as err:
        msg = f"corrupt log {str(path)!r}: {_describe(err)}"
        raise IngestError(msg) from err
    finally:
        reader.close()
    return [
        TopicSpan(name, "|".join(sorted(types[name])), counts[name], first.get(name, 0), last.get(name, 0))
        for name in sorted(types)
    ]


def survey_log(path: str | Path, overrides: Mapping[str, str] | None = None) -> LogSurvey:
    """Survey a log: topics with spans, the topic mapping, usability and what is missing.

    Args:
        path: ``.bag``, ``.db3``, ``.mcap`` or a ROS 2 bag directory.
        overrides: ``--topics`` overrides (keys ``image``, ``odometry``, ``ground_truth``).

    Returns:
        The survey; ``usable`` is False (with ``missing``/``reasons``) when ``process`` would refuse it.

    Raises:
        IngestError: missing path, not a log, unreadable storage, bad override.
    """
    log_path = Path(path)
    _check_path(log_path)
    spans = topic_spans(log_path)
    infos = [TopicInfo(t.name, t.msgtype, t.count, t.rate_hz) for t in spans]
    mapping = choose_topics(infos, overrides, source=str(log_path))
    stamped = [t for t in spans if t.count]
    survey = LogSurvey(
        path=log_path,
        topics=spans,
        mapping=mapping,
        start_ns=min((t.first_ns for t in stamped), default=0),
        end_ns=max((t.last_ns for t in stamped), default=0),
    )
    for role in REQUIRED_ROLES:
        if mapping.get(role) is None:
            survey.missing.append(role)
            survey.reasons[role] = ROLE_NEEDS[role]
    survey.motion = motion_source(mapping)
    for role in ("odometry", "ground_truth"):
        if mapping.get(role) is None and not (role == "odometry" and survey.motion == "navigation"):
            survey.notes.append(ROLE_NEEDS[role])
    if survey.motion == "navigation":
        sensors = "DVL + IMU + depth" if mapping.get("depth") else "DVL + IMU (no depth topic: z from the DVL)"
        survey.notes.append(f"no odometry topic: the motion is the {sensors} fusion (complementary filter)")
    elif mapping.get("dvl") and not mapping.get("imu"):
        survey.notes.append("a DVL topic without an IMU topic (sensor_msgs/Imu) is not used: no heading")
    if not survey.missing:
        try:
            with open_log(log_path, overrides) as log:
                survey.odometry_mode = log.odometry_mode
                survey.camera = read_camera(log)
        except IngestError as err:
            survey.missing.append("image")
            survey.reasons["image"] = str(err)
    return survey

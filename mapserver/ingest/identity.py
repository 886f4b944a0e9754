"""A mission log's identity: what a log is known by from the moment it is checked to the session it becomes.

A stored session is found by its log's SHA-256 and topic mapping; the frame count says when it is complete.
The three are read once, where the log is first opened (the REST upload's check, or ``process``), and
handed on as one :class:`LogIdentity` to whoever needs them (the job, the map-name choice, the pipeline,
the engine run), so nothing opens the log again or hashes it again to learn them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from mapserver.ingest.reader import MissionLog


@dataclass(frozen=True, slots=True)
class LogIdentity:
    """The identity of one mission log read with one topic mapping.

    Attributes:
        sha256: SHA-256 of the log file, or of a bag directory's files in sorted order
            (:attr:`MissionLog.sha256`).
        mapping: the topic mapping processing uses (:meth:`~mapserver.ingest.topics.TopicMapping.as_dict`).
        frames: camera frames in the log (:meth:`MissionLog.count_frames`).
    """

    sha256: str
    mapping: dict[str, str | None]
    frames: int

    @classmethod
    def of(cls, log: MissionLog, *, sha256: str | None = None) -> LogIdentity:
        """Return the identity of an open log.

        ``sha256``: the digest of the log's bytes when the caller has it already (an upload kept as it was
        received was hashed while it streamed in); None hashes the log now.
        """
        return cls(sha256=log.sha256 if sha256 is None else sha256, mapping=log.mapping.as_dict(),
                   frames=log.count_frames())  # fmt: skip

    def as_dict(self) -> dict[str, Any]:
        """Return ``{"sha256", "mapping", "frames"}`` (JSON: a queued job keeps it in its options)."""
        return {"sha256": self.sha256, "mapping": dict(self.mapping), "frames": self.frames}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> LogIdentity | None:
        """Return the identity :meth:`as_dict` wrote; None for None or an incomplete record (an older job's)."""
        if not isinstance(data, Mapping):
            return None
        sha256, mapping, frames = data.get("sha256"), data.get("mapping"), data.get("frames")
        if not isinstance(sha256, str) or not isinstance(mapping, Mapping) or not isinstance(frames, int):
            return None
        return cls(sha256=sha256, mapping=dict(mapping), frames=frames)

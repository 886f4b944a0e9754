"""Merge events as JSON: the match that triggered a merge and the record of what it did.

Stored in ``merge_events.details`` and ``merge_events.transform``; a redo rebuilds the merge from them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict
from typing import Any

import numpy as np

from core.se3 import quaternion_from_yaw
from mapserver.merge.record import Match, MergeRecord

RECORD_ARRAYS = ("template_map", "experience_map", "merge_links")
"""The per-row arrays of a :class:`MergeRecord` left out of its JSON summary (a redo recomputes them)."""


def record_summary(record: MergeRecord) -> dict[str, Any]:
    """Return a merge record as JSON without its per-row arrays (they are recomputed by a redo)."""
    data = record.to_dict()
    for key in RECORD_ARRAYS:
        data.pop(key, None)
    data["merge_links"] = int(np.asarray(record.merge_links).size)
    return data


def match_to_dict(match: Match) -> dict[str, Any]:
    """Return a match as JSON (see :func:`match_from_dict`)."""
    data = asdict(match)
    data["partial_pose"] = [float(v) for v in match.partial_pose]
    data["partial_packet"] = [float(v) for v in match.partial_packet]
    data["pairs"] = [[int(a), int(b)] for a, b in match.pairs]
    data["ties"] = [[int(a), int(b), [float(v) for v in t]] for a, b, t in match.ties]
    return data


def match_from_dict(data: Mapping[str, Any]) -> Match:
    """Rebuild a :class:`Match` from :func:`match_to_dict` output."""
    return Match(
        stored_template=int(data["stored_template"]),
        stored_experience=int(data["stored_experience"]),
        partial_template=int(data["partial_template"]),
        partial_pose=tuple(float(v) for v in data["partial_pose"]),
        partial_packet=tuple(float(v) for v in data["partial_packet"]),
        relative_rad=float(data["relative_rad"]),
        confirmations=int(data["confirmations"]),
        pairs=tuple((int(a), int(b)) for a, b in data["pairs"]),
        ties=tuple((int(a), int(b), tuple(float(v) for v in t)) for a, b, t in data.get("ties", ())),
    )


def transform7(record: MergeRecord) -> tuple[float, ...]:
    """Return the merge transform as (tx, ty, tz, qx, qy, qz, qw): the yaw as a quaternion about z."""
    x, y, z, yaw = record.transform
    return (x, y, z, *quaternion_from_yaw(yaw))

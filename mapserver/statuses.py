"""What a merge event's ``status`` may be: one enum, spelled nowhere else (the store, the atlas, the running session).

A :class:`~enum.StrEnum`, so a status compares equal to its text, is stored and sent in JSON as that text, and
the viewer and the REST API get its name.
"""

from __future__ import annotations

from enum import StrEnum


class MergeStatus(StrEnum):
    """A merge event's state: applied (in its map), undone (by ``unmerge``), rejected (rolled back by its probation)."""

    APPLIED = "applied"
    UNDONE = "undone"
    REJECTED = "rejected"

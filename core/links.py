"""The kinds of experience links: why a link exists (one owner for every layer, down to the viewer's names).

A module that imports nothing, so that every other one may use it (:mod:`core.robust` included, which
:mod:`core.experience_map` imports).
"""

from __future__ import annotations

from enum import IntEnum


class LinkKind(IntEnum):
    """Why a link exists (stored as int8)."""

    ODOMETRY = 0
    LOOP = 1
    MERGE = 2
    MANUAL = 3


SWITCHABLE_KINDS = (LinkKind.LOOP, LinkKind.MERGE, LinkKind.MANUAL)
"""The kinds that the robust relaxation may switch off: loop closures, merge links and manual links (an operator's
link that contradicts the map is flagged, switched off, never bent into it: ``mapserver link``)."""

"""Checking an engine snapshot before it is stored.

Optional per-row arrays (``em_link_active``, ``em_pc_lever``) are first fitted to their rows as the engine reads
them; then every row-table array's shape is checked against the templates, experiences, links and pose-cell links,
and its values (no NaN in a row table, finite poses, known link kinds, references in range, levers ≥ 0).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from core.experience_map import per_experience_array
from mapserver.errors import StoreError
from mapserver.store.models import LINK_KIND_NAMES
from mapserver.store.state_layout import ACTIVITY_KEY, ROW_FLOAT_KEYS


def _array(snapshot: Mapping[str, npt.ArrayLike], key: str) -> np.ndarray:
    """Return ``snapshot[key]`` as an array; a missing key is a :class:`StoreError`."""
    if key not in snapshot:
        msg = f"the snapshot lacks {key!r}"
        raise StoreError(msg)
    return np.asarray(snapshot[key])


@dataclass(frozen=True)
class Shapes:
    """A checked snapshot's sizes: templates (N, height, width), experiences, links, pose-cell links, lattice rank."""

    templates: int
    height: int
    width: int
    experiences: int
    links: int
    pc_links: int
    rank: int


def check_snapshot(snapshot: Mapping[str, npt.ArrayLike]) -> Shapes:
    """Validate the row-table arrays' shapes and values; return the sizes."""
    for key in snapshot:
        if key.startswith("__"):
            msg = f"snapshot key {key!r} is reserved (keys starting with '__')"
            raise StoreError(msg)
    shapes = _check_shapes(snapshot)
    _check_values(snapshot, shapes)
    return shapes


def _check_shapes(snapshot: Mapping[str, npt.ArrayLike]) -> Shapes:
    """Check every row-table array's shape against the templates, experiences, links and pose-cell links."""
    templates = _array(snapshot, "lv_templates")
    if templates.ndim != 3 or templates.dtype != np.float32:
        msg = f"lv_templates must be float32 (N, ty, tx), got {templates.dtype} {templates.shape!r}"
        raise StoreError(msg)
    n, h, w = templates.shape
    activity = _array(snapshot, ACTIVITY_KEY)
    rank = activity.ndim
    if rank not in (3, 4):
        msg = f"pc_activity must have 3 or 4 dimensions, got shape {activity.shape!r}"
        raise StoreError(msg)
    e = _array(snapshot, "em_pose").reshape(-1, 4).shape[0]
    k = _array(snapshot, "em_link_from").reshape(-1).shape[0]
    lpc = _array(snapshot, "pc_link_template").reshape(-1).shape[0]
    expected = {
        "lv_means": (n,), "lv_origin": (n,),
        "pc_link_coords": (lpc, rank), "pc_link_strength": (lpc,), "pc_link_decay": (lpc,),
        "em_pose": (e, 4), "em_pc": (e, rank), "em_template": (e,), "em_stamp": (e,), "em_origin": (e,),
        "em_link_to": (k,), "em_link_transform": (k, 4), "em_link_dt": (k,), "em_link_distance": (k,),
        "em_link_kind": (k,),
    }  # fmt: skip
    optional = {"em_link_active": (k,), "em_pc_lever": (e,)}
    expected.update({key: shape for key, shape in optional.items() if key in snapshot})
    for key, shape in expected.items():
        got = _array(snapshot, key).shape
        if got != shape:
            msg = f"snapshot {key!r} has shape {got!r}, expected {shape!r}"
            raise StoreError(msg)
    return Shapes(n, h, w, e, k, lpc, rank)


def _check_values(snapshot: Mapping[str, npt.ArrayLike], shapes: Shapes) -> None:
    """Check the values: no NaN in a row table, finite poses, known link kinds, ids in range, levers ≥ 0."""
    for key in ROW_FLOAT_KEYS:
        values = _array(snapshot, key)
        if values.size and not np.all(np.isfinite(values) | np.isinf(values)):
            row = int(np.flatnonzero(np.isnan(values.reshape(len(values), -1)).any(axis=1))[0])
            msg = f"snapshot {key!r} holds NaN (row {row}); a map with NaN cannot be stored"
            raise StoreError(msg)
    pose = _array(snapshot, "em_pose")
    if pose.size and not np.all(np.isfinite(pose)):
        row = int(np.flatnonzero(~np.isfinite(pose).all(axis=1))[0])
        msg = f"experience {row} has a non-finite pose {pose[row].tolist()!r}; a map with it cannot be stored"
        raise StoreError(msg)
    kinds = _array(snapshot, "em_link_kind")
    if kinds.size and (kinds.min() < 0 or kinds.max() >= len(LINK_KIND_NAMES)):
        msg = f"em_link_kind holds unknown codes {sorted(set(kinds.tolist()) - set(range(len(LINK_KIND_NAMES))))!r}"
        raise StoreError(msg)
    for key, limit, what in (
        ("em_template", shapes.templates, "templates"),
        ("pc_link_template", shapes.templates, "templates"),
        ("em_link_from", shapes.experiences, "experiences"),
        ("em_link_to", shapes.experiences, "experiences"),
    ):
        values = _array(snapshot, key)
        if values.size and (values.min() < 0 or values.max() >= limit):
            msg = f"snapshot {key!r} refers to {what} outside [0, {limit})"
            raise StoreError(msg)
    levers = _array(snapshot, "em_pc_lever") if "em_pc_lever" in snapshot else np.zeros(0)
    if levers.size and not (np.all(np.isfinite(levers)) and levers.min() >= 0.0):
        msg = "snapshot 'em_pc_lever' must hold finite lattice distances ≥ 0 (a merge's lever arms)"
        raise StoreError(msg)


def with_link_status(snapshot: Mapping[str, Any]) -> Mapping[str, Any]:
    """Return ``snapshot`` with ``em_link_active`` fitted to the links, as the engine reads it.

    A snapshot whose links were replaced may carry a status array of another length: links past
    its end are on, statuses past the last link are dropped (``ExperienceMap.restore``'s rule).
    """
    if "em_link_active" not in snapshot:
        return snapshot
    count = np.asarray(snapshot["em_link_from"]).reshape(-1).shape[0]
    given = np.asarray(snapshot["em_link_active"], dtype=bool).reshape(-1)
    if given.shape[0] == count:
        return snapshot
    active = np.ones(count, dtype=bool)
    active[: min(given.size, count)] = given[:count]
    return {**snapshot, "em_link_active": active}


def with_levers(snapshot: Mapping[str, Any]) -> Mapping[str, Any]:
    """Return ``snapshot`` with ``em_pc_lever`` fitted to the experiences, as the engine reads it.

    A snapshot whose experiences were replaced (an importer starting from an empty engine's snapshot) may
    carry levers of another length: experiences past its end have lever 0 (no merge moved them), levers past
    the last experience are dropped (``ExperienceMap.restore``'s rule).
    """
    if "em_pc_lever" not in snapshot:
        return snapshot
    count = np.asarray(snapshot["em_pose"]).reshape(-1, 4).shape[0]
    if np.asarray(snapshot["em_pc_lever"]).reshape(-1).shape[0] == count:
        return snapshot
    return {**snapshot, "em_pc_lever": per_experience_array(snapshot, "em_pc_lever", count)}

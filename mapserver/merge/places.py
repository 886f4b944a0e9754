"""Where each view cell was made: template places in the stored map and through a merge.

The engine records, for every view cell (template) it makes, the experience current at that frame and
the odometry accumulated since it (snapshot ``lv_place``, ``lv_place_offset``; docs/architecture.md). A
view cell's *place* is then that experience's pose plus the offset (x, y, z in the map frame; heading
absolute), so it follows the experience through relaxation. Most view cells of the ``sdr-htm`` front-end
have no experience of their own (a new view cell nearly every frame, experiences only where the gates
allow one), so its merge observations locate a matched view cell by its place (:mod:`mapserver.merge.online`).

A merge keeps the loaded map's places and moves the partial map's with it: their experience renumbered
(``MergeRecord.experience_map``), their offset turned by the merge transform's yaw (as the robot's own
accumulated odometry, Algorithm 1 operation (iv)).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from core.engine import template_place_rows
from core.se3 import wrap_angle
from mapserver.merge.record import MergeRecord

State = Mapping[str, np.ndarray]


def _rows(state: State) -> tuple[np.ndarray, np.ndarray]:
    """Return (place (N,), offset (N, 4)) of a snapshot's templates; rows without one: −1 and zeros."""
    return template_place_rows(state, int(np.shape(state["lv_means"])[0]))


def template_places(state: State) -> tuple[np.ndarray, np.ndarray]:
    """Return (pose (N, 4), experience (N,)) of every template's place; −1 where it has none.

    pose = the experience's (x, y, z) + the offset's (x, y, z), heading = the offset's (absolute) heading.
    """
    place, offset = _rows(state)
    poses = np.asarray(state["em_pose"], dtype=np.float64).reshape(-1, 4)
    place[(place < 0) | (place >= poses.shape[0])] = -1
    out = np.full((place.size, 4), np.nan)
    ok = place >= 0
    out[ok, :3] = poses[place[ok], :3] + offset[ok, :3]
    out[ok, 3] = offset[ok, 3]
    return out, place


def merged_template_places(loaded: State, partial: State, record: MergeRecord) -> dict[str, np.ndarray]:
    """Return ``lv_place`` and ``lv_place_offset`` of the merged snapshot ``merge_states`` made from these two."""
    l_place, l_offset = _rows(loaded)
    p_place, p_offset = _rows(partial)
    kept = np.asarray(record.template_map) >= record.template_offset
    p_place, p_offset = p_place[kept], p_offset[kept].copy()
    emap = np.asarray(record.experience_map, dtype=np.int64)
    has = (p_place >= 0) & (p_place < emap.size)
    p_place = np.where(has, emap[np.clip(p_place, 0, max(emap.size - 1, 0))] if emap.size else -1, -1)
    yaw = float(record.transform[3])
    c, s = math.cos(yaw), math.sin(yaw)
    x, y = p_offset[:, 0].copy(), p_offset[:, 1].copy()
    p_offset[:, 0], p_offset[:, 1] = c * x - s * y, s * x + c * y
    p_offset[:, 3] = wrap_angle(p_offset[:, 3] + yaw)
    return {
        "lv_place": np.concatenate([l_place, p_place]).astype(np.int64),
        "lv_place_offset": np.concatenate([l_offset, p_offset]),
    }

"""Where each view cell was made: template places in the stored map and through a merge.

The engine records, for every view cell (template) it makes, the experience current at that frame and
the odometry accumulated since it (snapshot ``lv_place``, ``lv_place_offset``; docs/architecture.md). A
view cell's *place* is then that experience's pose plus the offset (x, y, z in the map frame; heading
absolute), so it follows the experience through relaxation. Most view cells of the ``sdr-htm`` front-end
have no experience of their own (a new view cell nearly every frame, experiences only where the gates
allow one), so its merge observations locate a matched view cell by its place (:mod:`mapserver.merge.online`).

The offset is recorded in the map frame, with the experience's heading at that moment
(``lv_place_yaw``): when relaxation later turns the experience, the place turns with it (the offset rotated
by the experience's turn since, the facing too). Without that, a view cell's place kept its first facing
while its experience turned: on ``cave3d`` (session 1 alone, settled) places came out 30–42° off the way
their views were seen, and the merge's observations missed there. Snapshots made before the key have no
yaw: their offsets are used as stored.

A merge keeps the loaded map's places and moves the partial map's with it: their experience renumbered
(``MergeRecord.experience_map``), their offset and recorded yaw turned by the merge transform's yaw (as
the robot's own accumulated odometry, Algorithm 1 operation (iv)).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from core.angles import wrap_angle
from core.arrays import FloatArray, IntArray, UInt8Array
from core.engine import template_place_rows, template_place_yaws, template_rows
from core.se3 import compose
from core.snapshot import ExperienceMapSnapshot, ViewSnapshot
from mapserver.merge.record import MergeRecord

State = Mapping[str, np.ndarray]

MEANS, SDR = ViewSnapshot.key("means"), ViewSnapshot.key("sdr")
POSE = ExperienceMapSnapshot.key("pose")


def _rows(state: State) -> tuple[IntArray, FloatArray]:
    """Return (place (N,), offset (N, 4)) of a snapshot's templates; rows without one: −1 and zeros."""
    return template_place_rows(state, int(np.shape(state[MEANS])[0]))


def template_places(state: State) -> tuple[FloatArray, IntArray]:
    """Return (pose (N, 4), experience (N,)) of every template's place; −1 where it has none.

    With t = the experience's heading now − its heading when the template was made (``lv_place_yaw``; 0
    when unknown): pose = the experience's (x, y, z) + the offset's (x, y) turned by t (z as it is), heading =
    the offset's heading + t.
    """
    place, offset = _rows(state)
    poses = np.asarray(state[POSE], dtype=np.float64).reshape(-1, 4)
    place[(place < 0) | (place >= poses.shape[0])] = -1
    out = np.full((place.size, 4), np.nan)
    ok = place >= 0
    base = poses[place[ok]].copy()
    turn = wrap_angle(base[:, 3] - template_place_yaws(state, place.size)[ok])
    base[:, 3] = np.where(np.isnan(turn), 0.0, turn)  # no yaw recorded: the offset as stored
    out[ok] = compose(base, offset[ok])  # the experience's position, turned since by ``turn``
    return out, place


def merged_template_places(loaded: State, partial: State, record: MergeRecord) -> dict[str, np.ndarray]:
    """Return ``lv_place``, ``lv_place_offset`` and ``lv_place_yaw`` of the merged snapshot ``merge_states`` made."""
    l_place, l_offset = _rows(loaded)
    p_place, p_offset = _rows(partial)
    l_yaw = template_place_yaws(loaded, l_place.size)
    kept = np.asarray(record.template_map) >= record.template_offset
    p_place, p_offset = p_place[kept], p_offset[kept].copy()
    p_yaw = template_place_yaws(partial, kept.size)[kept]
    emap = np.asarray(record.experience_map, dtype=np.int64)
    has = (p_place >= 0) & (p_place < emap.size)
    p_place = np.where(has, emap[np.clip(p_place, 0, max(emap.size - 1, 0))] if emap.size else -1, -1)
    yaw = float(record.transform[3])
    p_offset = compose(np.array([0.0, 0.0, 0.0, yaw]), p_offset)  # turned by T's yaw, as the robot's odometry
    view = ViewSnapshot
    return {
        view.key("place"): np.concatenate([l_place, p_place]).astype(np.int64),
        view.key("place_offset"): np.concatenate([l_offset, p_offset]),
        view.key("place_yaw"): np.concatenate([l_yaw, wrap_angle(p_yaw + yaw)]),  # NaN (unknown) stays NaN
    }


def merged_template_codes(loaded: State, partial: State, record: MergeRecord) -> dict[str, UInt8Array]:
    """Return ``lv_sdr`` of the merged snapshot: the loaded view cells' codes, then the partial's kept ones.

    ``sdr-htm`` view cells keep the packed SDR of the frame that made it (``core.neocortex``); a map made
    before the key existed has zero codes. Empty when neither snapshot has codes (``lvc`` maps).
    """
    if SDR not in loaded and SDR not in partial:
        return {}
    width = int(np.shape(loaded[SDR] if SDR in loaded else partial[SDR])[1])
    l_codes, p_codes = (template_rows(s, SDR, int(np.shape(s[MEANS])[0]), 0, np.uint8, width)
                        for s in (loaded, partial))  # fmt: skip
    kept = np.asarray(record.template_map) >= record.template_offset
    return {SDR: np.concatenate([l_codes, p_codes[kept]])}

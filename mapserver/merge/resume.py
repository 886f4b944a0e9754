"""The online merge driver's state between two frames, as plain arrays (``process --stop-after``, then resume)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol, cast

import numpy as np

from core.arrays import FloatArray
from mapserver.merge.confirm import Observation
from mapserver.merge.hypotheses import Hypothesis, Track

if TYPE_CHECKING:
    from mapserver.merge.online import _Candidate

_HYPOTHESIS_COLUMNS = 22  # key, born, hit_m, miss_m, post_hit_m, post_miss_m, alignment (4), turn (3), held (5),
# anchor place (4)
_HYPOTHESIS_COLUMNS_BEFORE_ANCHOR = 18  # states stored before ``Hypothesis.anchor_place``: none anchored
_HYPOTHESIS_COLUMNS_BEFORE_HELD = 13  # states stored before ``Hypothesis.held_place``: none held
_SUPPORT_COLUMNS = 15  # hypothesis row, frame, template, experience, error, relative, partial template, odometry, seen


def _observation_row(row: int, o: Observation) -> FloatArray:
    head = [float(row), float(o.frame), float(o.stored_template), float(o.stored_experience), o.error,
            o.relative_rad, float(o.partial_template)]  # fmt: skip
    return np.concatenate([head, o.odometry, o.seen, o.packet]).astype(np.float64)


def _observation(row: FloatArray) -> Observation:
    return Observation(
        frame=int(row[1]), stored_template=int(row[2]), stored_experience=int(row[3]), error=float(row[4]),
        relative_rad=float(row[5]), partial_template=int(row[6]), odometry=row[7:11].copy(),
        seen=row[11:15].copy(), packet=row[_SUPPORT_COLUMNS:].copy(),
    )  # fmt: skip


@dataclass(frozen=True, eq=False)
class MergerState:
    """The online driver's state between two frames, for resuming a session later.

    Attributes:
        odometry: (4,) the session's odometry pose so far (x, y, z, yaw).
        absorbed: keys of the maps merged so far.
        hypotheses: stored-map key → (live hypotheses, banned alignments).
        track: the session's recent frames (None: none yet).
    """

    odometry: FloatArray
    absorbed: tuple[object, ...] = ()
    hypotheses: Mapping[object, tuple[tuple[Hypothesis, ...], tuple[FloatArray, ...]]] = field(default_factory=dict)
    track: Track | None = None
    readers: tuple[tuple[object, Mapping[str, np.ndarray]], ...] = ()
    """sdr-htm sessions: every candidate's cortex reader (key, :meth:`CortexReader.state`), in view-row order."""

    def without(self, keys: Sequence[object]) -> MergerState:
        """Return the state with the hypotheses of these maps dropped (maps that changed since).

        With cortex readers, one changed map restarts them all (the track's views hold every reader's row).
        """
        gone = set(keys)
        if self.readers and gone & {k for k, _ in self.readers}:
            return MergerState(self.odometry, self.absorbed)
        kept = {k: v for k, v in self.hypotheses.items() if k not in gone}
        return MergerState(self.odometry, self.absorbed, kept, self.track, self.readers)

    def restore_into(self, candidates: Sequence[_Candidate], track: Track) -> None:
        """Put the hypotheses back into the candidates' sets and the frames into ``track``."""
        for candidate in candidates:
            live, banned = self.hypotheses.get(candidate.stored.key, ((), ()))
            candidate.hypotheses.hypotheses = [_copy(h) for h in live]
            candidate.hypotheses.banned = [b.copy() for b in banned]
        if self.track is not None:
            track.frames.extend(self.track.frames)
            track.distance = self.track.distance

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Return the state as plain arrays (map keys must be integers).

        Keys: ``odometry``, ``absorbed``, ``hypotheses`` (H, 22): key, born, hit_m, miss_m,
        post_hit_m, post_miss_m, alignment (4), turn (3), held place (4; NaN: none), held_m, anchor place
        (4; NaN: none);
        ``support`` (S, 15 + D): hypothesis row, frame,
        stored template, stored experience, error, relative_rad, partial template, odometry (4),
        seen (4), packet (D); ``hits`` (N, 9): hypothesis row, odometry (4), place (4) (``Hypothesis.hits``;
        a state stored before them has none); ``banned`` (B, 5): key, alignment; ``track_*``: the recent frames.
        """
        rows: list[list[float]] = []
        support: list[FloatArray] = []
        banned: list[list[float]] = []
        hits: list[list[float]] = []
        for key, (live, bans) in self.hypotheses.items():
            for h in live:
                rows.append([float(int(cast(int, key))), float(h.born), h.hit_m, h.miss_m, h.post_hit_m, h.post_miss_m,
                             *h.alignment, *h.turn, *_held_row(h), *_place_row(h.anchor_place)])  # fmt: skip
                support.extend(_observation_row(len(rows) - 1, o) for o in h.support)
                hits.extend([float(len(rows) - 1), *odometry, *place] for odometry, place in h.hits)
            banned.extend([float(int(cast(int, key))), *b] for b in bans)
        width = max((r.size for r in support), default=_SUPPORT_COLUMNS)
        frames = list(self.track.frames) if self.track is not None else []
        views = np.stack([f[3] for f in frames]) if frames else np.zeros((0, 0, 0), dtype=np.float32)
        return {
            "odometry": np.asarray(self.odometry, dtype=np.float64).reshape(4).copy(),
            "absorbed": np.asarray([int(cast(int, k)) for k in self.absorbed], dtype=np.int64),
            "hypotheses": np.asarray(rows, dtype=np.float64).reshape(-1, _HYPOTHESIS_COLUMNS),
            "support": np.vstack(support) if support else np.zeros((0, width), dtype=np.float64),
            "banned": np.asarray(banned, dtype=np.float64).reshape(-1, 5),
            "hits": np.asarray(hits, dtype=np.float64).reshape(-1, 9),
            "track_frames": np.asarray([f[0] for f in frames], dtype=np.int64),
            "track_odometry": np.asarray([f[1] for f in frames], dtype=np.float64).reshape(-1, 4),
            "track_distance": np.asarray([f[2] for f in frames], dtype=np.float64),
            "track_views": views.astype(np.float32),
            "track_means": np.asarray([f[4] for f in frames], dtype=np.float64),
            "track_total": np.asarray([0.0 if self.track is None else self.track.distance], dtype=np.float64),
            "readers": np.asarray([int(cast(int, k)) for k, _ in self.readers], dtype=np.int64),
            **{f"reader{r}_{name}": v for r, (_, state) in enumerate(self.readers) for name, v in state.items()},
        }

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> MergerState:
        """Rebuild a state from :meth:`to_arrays` output."""
        stored = np.asarray(arrays["hypotheses"], dtype=np.float64)
        width = stored.shape[1] if stored.ndim == 2 and stored.size else _HYPOTHESIS_COLUMNS
        table = stored.reshape(-1, width)
        old, unanchored = width == _HYPOTHESIS_COLUMNS_BEFORE_HELD, width <= _HYPOTHESIS_COLUMNS_BEFORE_ANCHOR
        support = np.asarray(arrays["support"], dtype=np.float64)
        made = [
            Hypothesis(alignment=r[6:10].copy(), born=int(r[1]), hit_m=float(r[2]), miss_m=float(r[3]),
                       post_hit_m=float(r[4]), post_miss_m=float(r[5]), turn=r[10:13].copy(),
                       held_place=None if old or np.isnan(r[13]) else r[13:17].copy(),
                       held_m=0.0 if old else float(r[17]),
                       anchor_place=None if unanchored or np.isnan(r[18]) else r[18:22].copy())
            for r in table
        ]  # fmt: skip
        for row in support:
            made[int(row[0])].support.append(_observation(row))
        for row in np.asarray(arrays.get("hits", np.zeros((0, 9))), dtype=np.float64).reshape(-1, 9):
            made[int(row[0])].hits.append((row[1:5].copy(), row[5:9].copy()))
        grouped: dict[int, tuple[list[Hypothesis], list[FloatArray]]] = {}
        for r, h in zip(table, made, strict=True):
            grouped.setdefault(int(r[0]), ([], []))[0].append(h)
        for r in np.asarray(arrays["banned"], dtype=np.float64).reshape(-1, 5):
            grouped.setdefault(int(r[0]), ([], []))[1].append(r[1:].copy())
        hypotheses: dict[object, tuple[tuple[Hypothesis, ...], tuple[FloatArray, ...]]] = {
            k: (tuple(v[0]), tuple(v[1])) for k, v in sorted(grouped.items())
        }
        track = Track(0.0)
        views = np.asarray(arrays["track_views"], dtype=np.float32)
        odometry, distance = np.asarray(arrays["track_odometry"]), np.asarray(arrays["track_distance"])
        means = np.asarray(arrays["track_means"])
        for i, frame in enumerate(np.asarray(arrays["track_frames"], dtype=np.int64)):
            track.frames.append((int(frame), odometry[i].copy(), float(distance[i]), views[i].copy(), float(means[i])))
        track.distance = float(np.asarray(arrays["track_total"]).reshape(-1)[0])
        absorbed = tuple(int(k) for k in np.asarray(arrays["absorbed"], dtype=np.int64).reshape(-1))
        keys = np.asarray(arrays.get("readers", np.zeros(0)), dtype=np.int64).reshape(-1)
        readers = tuple(
            (int(k), {name[len(f"reader{r}_"):]: v for name, v in arrays.items() if name.startswith(f"reader{r}_")})
            for r, k in enumerate(keys)
        )
        odometry = np.asarray(arrays["odometry"], dtype=np.float64).reshape(4).copy()
        return cls(odometry, absorbed, hypotheses, track, readers)


def _copy(h: Hypothesis) -> Hypothesis:
    return Hypothesis(
        alignment=h.alignment.copy(), born=h.born, support=list(h.support), hit_m=h.hit_m, miss_m=h.miss_m,
        post_hit_m=h.post_hit_m, post_miss_m=h.post_miss_m, turn=h.turn.copy(),
        held_place=None if h.held_place is None else h.held_place.copy(), held_m=h.held_m,
        anchor_place=None if h.anchor_place is None else h.anchor_place.copy(), hits=list(h.hits),
    )  # fmt: skip


def _place_row(place: FloatArray | None) -> list[float]:
    return [math.nan] * 4 if place is None else [float(v) for v in place]


def _held_row(h: Hypothesis) -> list[float]:
    return [*_place_row(h.held_place), float(h.held_m)]


MERGER_PREFIX = "mg_"
"""Snapshot keys of the merge driver's state (stored with a partial session's map)."""


class VersionedMap(Protocol):
    """A stored map as the resume reads it (``mapserver.atlas.AtlasMap``): its id, version and engine snapshot."""

    @property
    def id(self) -> int:
        """Return the map's id in the store."""

    @property
    def version(self) -> int:
        """Return the map's version (raised by every write)."""

    @property
    def snapshot(self) -> Mapping[str, np.ndarray]:
        """Return the map's engine snapshot (its ``mg_*`` keys: the driver's state)."""


def resume_merger_state(
    stored: VersionedMap, session_id: int, candidates: Sequence[VersionedMap]
) -> MergerState | None:
    """Return the merge driver's state a partial session left in its map (None: none stored).

    Hypotheses are kept only when the map is still at the version the session wrote and the candidate
    map is at the version they were built against; otherwise they restart (the odometry and track stay).
    """
    snap = stored.snapshot
    if "mg_session" not in snap or "mg_hypotheses" not in snap or int(snap["mg_session"]) != session_id:
        return None
    arrays = {k[len(MERGER_PREFIX) :]: v for k, v in snap.items() if k.startswith(MERGER_PREFIX)}
    state = MergerState.from_arrays(arrays)
    if int(snap["mg_map_version"]) != stored.version:
        return state.without(list(state.hypotheses))
    versions = {int(k): int(v) for k, v in np.asarray(snap.get("mg_versions", np.zeros((0, 2))), np.int64)}
    current = {c.id: c.version for c in candidates}
    stale = [k for k in state.hypotheses if versions.get(int(cast(int, k))) != current.get(int(cast(int, k)))]
    return state.without(stale)


def merger_keys(
    state: MergerState, *, session_id: int, map_version: int, candidates: Sequence[VersionedMap]
) -> dict[str, np.ndarray]:
    """Return the ``mg_*`` snapshot keys that let a partial session resume its merge driver."""
    arrays = state.to_arrays()
    out = {MERGER_PREFIX + k: v for k, v in arrays.items()}
    out["mg_session"] = np.asarray(session_id, dtype=np.int64)
    out["mg_map_version"] = np.asarray(map_version, dtype=np.int64)
    out["mg_versions"] = np.asarray([[c.id, c.version] for c in candidates], dtype=np.int64).reshape(-1, 2)
    return out

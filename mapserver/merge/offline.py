"""Offline merge of two stored maps (``mapserver merge --map A --into B``).

Map A's views, taken in creation order (which follows A's trajectory), are matched against map B's
with B's matcher and threshold (:mod:`mapserver.merge.offline_views`: LVC templates with
``LocalViewCells.match``, vectorised over B's templates; ``sdr-htm`` view cells by their codes'
overlap recall). A run of consecutive matching A views is confirmed by the same rule as online
(:mod:`mapserver.merge.confirm`), where A saw each view standing in for the odometry: the matched B
places must advance as A's do, under one rigid alignment. The best-supported run is the one with the
most agreeing views (then the lowest mean error); it must hold K of them (K from ``--confirm`` or A's
``Params.merge_confirm``) and two distinct B views when K ≥ 2. A is then merged into B anchored at the
run's best-matching view, every pair of the run identified.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from core import Engine
from core.se3 import compose, relative
from mapserver.errors import MergeError, NoConfirmedMatchError
from mapserver.merge.confirm import Observation, Streak
from mapserver.merge.engines import StoredMap, merge_snapshots
from mapserver.merge.offline_views import (
    PartialViews,
    StoredViews,
    offline_incompatibility,
    partial_views,
    stored_views,
)
from mapserver.merge.online import DEFAULT_YAW_TOLERANCE, default_position_tolerance
from mapserver.merge.record import Match, MergeRecord
from mapserver.merge.snapshot import State

logger = logging.getLogger(__name__)


def find_match(
    partial: StoredMap,
    loaded: StoredMap,
    *,
    confirm: int | None = None,
    position_tolerance: float | None = None,
    yaw_tolerance: float = DEFAULT_YAW_TOLERANCE,
) -> Match:
    """Return the best-supported confirmed match of map ``partial``'s templates in map ``loaded``.

    The first of :func:`candidate_matches` (same arguments and errors).
    """
    return candidate_matches(
        partial, loaded, confirm=confirm, position_tolerance=position_tolerance, yaw_tolerance=yaw_tolerance
    )[0]


def candidate_matches(
    partial: StoredMap,
    loaded: StoredMap,
    *,
    confirm: int | None = None,
    position_tolerance: float | None = None,
    yaw_tolerance: float = DEFAULT_YAW_TOLERANCE,
) -> list[Match]:
    """Return one match per confirmed run of map ``partial``'s templates in map ``loaded``, best first.

    Runs are ranked by agreeing templates, then by mean error; each is anchored at its best template.

    Args:
        partial: map A (merged into ``loaded``).
        loaded: map B.
        confirm: K, agreeing templates needed; None → A's ``Params.merge_confirm``.
        position_tolerance: metres; None → :func:`default_position_tolerance` of B.
        yaw_tolerance: radians.

    Raises:
        MergeError: the maps cannot be merged (parameters, empty map).
        NoConfirmedMatchError: no run of K agreeing matching templates exists (the message says how
            many the best run had; a :class:`MergeError` that exits 2).
    """
    needed = _needed_confirmations(partial, loaded, confirm)
    tolerance = position_tolerance if position_tolerance is not None else default_position_tolerance(loaded)
    n_a, n_b = int(np.shape(partial.snapshot.view.means)[0]), int(np.shape(loaded.snapshot.view.means)[0])
    if n_a == 0 or n_b == 0:
        empty = partial.key if n_a == 0 else loaded.key
        msg = f"map {empty!r} has no templates to match"
        raise MergeError(msg)
    threshold = loaded.params.vt_match_threshold
    mine, theirs = partial_views(partial), stored_views(loaded, loaded.params, tolerance)
    scan = _scan_runs(mine, theirs, threshold, Streak(needed, tolerance, yaw_tolerance))
    if not scan.runs:
        what = "view cell" if theirs.loose else "template"
        if scan.matched == 0:
            msg = f"no {what} of map {partial.key!r} matches map {loaded.key!r} (threshold {threshold!r})"
        else:
            msg = (
                f"no confirmed match of map {partial.key!r} in map {loaded.key!r}: {scan.matched} {what}s match "
                f"but the longest agreeing run has {scan.longest} (needs {needed}, along two distinct stored "
                f"{what}s)"
            )
        raise NoConfirmedMatchError(msg)
    ranked = sorted(scan.runs.values(), key=lambda r: _score(r[0]), reverse=True)
    return [_match_of(partial.state, mine, theirs, entries, pairs) for entries, pairs in ranked]


def _needed_confirmations(partial: StoredMap, loaded: StoredMap, confirm: int | None) -> int:
    """Return K, the agreeing templates a run needs, once the maps are known to be mergeable."""
    reason = offline_incompatibility(loaded, partial)
    if reason:
        msg = f"cannot merge map {partial.key!r} into {loaded.key!r}: {reason}"
        raise MergeError(msg)
    needed = confirm if confirm is not None else partial.params.merge_confirm
    if needed < 1:
        msg = f"--confirm must be at least 1, got {needed!r}"
        raise MergeError(msg)
    return needed


@dataclass
class _Scan:
    """What the scan of A's templates found: each run's best confirmed state, matching templates, longest run."""

    runs: dict[int, tuple[list[Observation], tuple[tuple[int, int], ...]]] = field(default_factory=dict)
    matched: int = 0
    longest: int = 0


def _scan_runs(mine: PartialViews, theirs: StoredViews, threshold: float, streak: Streak) -> _Scan:
    """Match A's views in creation order against B's; return every run's best confirmed state."""
    scan = _Scan()
    run = 0
    for i in range(mine.means.shape[0]):
        u, error, rel = theirs.matcher.match(mine.views[i], float(mine.means[i]), limit=threshold)
        if u < 0 or error > threshold:
            streak.reset()
            run += 1
            continue
        scan.matched += 1
        before = len(streak.entries)
        streak.add(_observation(mine, theirs, streak, i, u, error, rel))
        run += len(streak.entries) <= before  # the streak restarted: a new run
        scan.longest = max(scan.longest, len(streak.entries))
        if streak.confirmed and _score(streak.entries) > _score(scan.runs.get(run, ([], ()))[0]):
            scan.runs[run] = (list(streak.entries), streak.pairs())
    return scan


def _observation(
    mine: PartialViews, theirs: StoredViews, streak: Streak, i: int, u: int, error: float, rel: float
) -> Observation:
    """Return A's view ``i`` matching B's view ``u`` as an observation of the streak.

    Where u has several places, the one nearest the streak's prediction.
    """
    seen_at = int(mine.experiences[i])
    places = theirs.places_of(u)
    place = -1
    if places.size and seen_at >= 0:
        predicted = streak.predict(mine.poses[i])
        if predicted is None or places.size == 1:
            place = int(places[0])
        else:
            distances = np.linalg.norm(theirs.poses[places, :3] - predicted[:3], axis=1)
            place = int(places[int(np.argmin(distances))])
    seen = compose(theirs.poses[place], np.array([0.0, 0.0, 0.0, rel])) if place >= 0 else np.zeros(4)
    return Observation(
        frame=i,
        stored_template=u,
        stored_experience=int(theirs.experiences[place]) if place >= 0 else -1,
        error=float(error),
        relative_rad=float(rel),
        partial_template=i,
        odometry=mine.poses[i] if seen_at >= 0 else np.zeros(4),
        packet=mine.packets[i] if seen_at >= 0 else np.zeros(mine.packets.shape[1]),
        seen=seen,
    )


def _score(entries: list[Observation]) -> tuple[int, float]:
    """A run's rank: the most agreeing templates, then the lowest mean error."""
    return (len(entries), -float(np.mean([e.error for e in entries])) if entries else 0.0)


def _match_of(
    a: State, mine: PartialViews, theirs: StoredViews, entries: list[Observation], pairs: tuple[tuple[int, int], ...]
) -> Match:
    """The match of one confirmed run, anchored at its best-matching (latest on ties) view.

    LVC: A's experience of that template ↔ B's experience (the paper's e_z ↔ e_u). ``sdr-htm``: the view was
    seen at a place of B's, generally off its experience; A's pose is moved by the same offset so that the
    anchor is B's experience (as online, :meth:`mapserver.merge.online.OnlineMerger._merge`).
    """
    anchor = min(reversed(entries), key=lambda e: e.error)
    heading = np.array([0.0, 0.0, 0.0, anchor.relative_rad])
    if not theirs.loose:
        exp_a = int(mine.experiences[anchor.partial_template])
        return Match.at_experience(
            a, exp_a, anchor.stored_template, anchor.stored_experience, relative_rad=anchor.relative_rad,
            confirmations=len(entries), pairs=pairs,
        )  # fmt: skip
    experience = compose(theirs.poses[anchor.stored_experience], heading)  # experiences are B's first places
    pose = compose(anchor.odometry, relative(anchor.seen, experience))
    return Match(
        stored_template=anchor.stored_template, stored_experience=anchor.stored_experience,
        partial_template=anchor.partial_template, partial_pose=tuple(float(v) for v in pose),
        partial_packet=tuple(float(v) for v in anchor.packet), relative_rad=anchor.relative_rad,
        confirmations=len(entries), pairs=pairs,
    )  # fmt: skip


def merge_maps(
    partial: StoredMap,
    loaded: StoredMap,
    *,
    confirm: int | None = None,
    shift_lattice: bool = True,
    position_tolerance: float | None = None,
    yaw_tolerance: float = DEFAULT_YAW_TOLERANCE,
) -> tuple[Engine, MergeRecord]:
    """Merge stored map ``partial`` (A) into stored map ``loaded`` (B); return the merged engine and record.

    Raises:
        MergeError: incompatible maps or no confirmed match (see :func:`find_match`).
    """
    match = find_match(
        partial, loaded, confirm=confirm, position_tolerance=position_tolerance, yaw_tolerance=yaw_tolerance
    )
    logger.info(
        "merging map %r into %r at template %d ↔ %d (%d confirmations)",
        partial.key, loaded.key, match.partial_template, match.stored_template, match.confirmations,
    )
    return merge_snapshots(loaded, partial, match, shift_lattice=shift_lattice)

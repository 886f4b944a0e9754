"""Offline merge of two stored maps (``mapserver merge --map A --into B``).

Map A's templates, taken in creation order (which follows A's trajectory), are matched
against map B's with B's matcher and threshold (``LocalViewCells.match``, vectorised over
B's templates). A run of consecutive matching A templates is confirmed by the same rule
as online (:mod:`mapserver.merge.confirm`), A's experience poses standing in for the
odometry: the matched B experiences must advance as A's experiences do, under one rigid
alignment. The best-supported run is the one with the most agreeing templates (then the
lowest mean error); it must hold K of them (K from ``--confirm`` or A's
``Params.merge_confirm``) and two distinct B templates when K ≥ 2. A is then merged into B
anchored at the run's best-matching template, every pair of the run identified.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core import Engine
from core.localview import LocalViewCells
from core.se3 import compose
from mapserver.errors import MergeError, NoConfirmedMatchError
from mapserver.merge.confirm import Observation, Streak
from mapserver.merge.engines import StoredMap, merge_snapshots
from mapserver.merge.online import DEFAULT_YAW_TOLERANCE, default_position_tolerance
from mapserver.merge.record import Match, MergeRecord
from mapserver.merge.snapshot import experiences_by_template, params_incompatibility

logger = logging.getLogger(__name__)


def _experience_for(order: np.ndarray, starts: np.ndarray, template: int) -> np.ndarray:
    return order[starts[template] : starts[template + 1]]


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
    n_a, n_b = int(np.shape(partial.state["lv_means"])[0]), int(np.shape(loaded.state["lv_means"])[0])
    if n_a == 0 or n_b == 0:
        empty = partial.key if n_a == 0 else loaded.key
        msg = f"map {empty!r} has no templates to match"
        raise MergeError(msg)
    cells = LocalViewCells.restore(loaded.params, loaded.state)
    threshold = loaded.params.vt_match_threshold
    arrays = _MatchArrays.of(partial.state, loaded.state, n_a, n_b)
    scan = _scan_runs(cells, threshold, arrays, Streak(needed, tolerance, yaw_tolerance))
    if not scan.runs:
        if scan.matched == 0:
            msg = f"no template of map {partial.key!r} matches map {loaded.key!r} (threshold {threshold!r})"
        else:
            msg = (
                f"no confirmed match of map {partial.key!r} in map {loaded.key!r}: {scan.matched} templates match "
                f"but the longest agreeing run has {scan.longest} (needs {needed}, along two distinct stored "
                "templates)"
            )
        raise NoConfirmedMatchError(msg)
    ranked = sorted(scan.runs.values(), key=lambda r: _score(r[0]), reverse=True)
    return [_match_of(partial.state, arrays.a_order, arrays.a_starts, entries, pairs) for entries, pairs in ranked]


def _needed_confirmations(partial: StoredMap, loaded: StoredMap, confirm: int | None) -> int:
    """Return K, the agreeing templates a run needs, once the maps are known to be mergeable."""
    reason = params_incompatibility(loaded.params, partial.params)
    if reason:
        msg = f"cannot merge map {partial.key!r} into {loaded.key!r}: {reason}"
        raise MergeError(msg)
    needed = confirm if confirm is not None else partial.params.merge_confirm
    if needed < 1:
        msg = f"--confirm must be at least 1, got {needed!r}"
        raise MergeError(msg)
    return needed


@dataclass(frozen=True)
class _MatchArrays:
    """A's templates and experience poses and both maps' template → experience indices, as the scan reads them."""

    a_templates: np.ndarray
    a_means: np.ndarray
    a_order: np.ndarray
    a_starts: np.ndarray
    b_order: np.ndarray
    b_starts: np.ndarray
    a_pose: np.ndarray
    a_pc: np.ndarray
    b_pose: np.ndarray

    @classmethod
    def of(cls, a: Any, b: Any, n_a: int, n_b: int) -> _MatchArrays:
        """Return the arrays of snapshots ``a`` (map A, ``n_a`` templates) and ``b`` (map B, ``n_b``)."""
        a_order, a_starts = experiences_by_template(np.asarray(a["em_template"]), n_a)
        b_order, b_starts = experiences_by_template(np.asarray(b["em_template"]), n_b)
        a_pose = np.asarray(a["em_pose"], dtype=np.float64).reshape(-1, 4)
        return cls(
            a_templates=np.asarray(a["lv_templates"], dtype=np.float32),
            a_means=np.asarray(a["lv_means"], dtype=np.float64),
            a_order=a_order,
            a_starts=a_starts,
            b_order=b_order,
            b_starts=b_starts,
            a_pose=a_pose,
            a_pc=np.asarray(a["em_pc"], dtype=np.float64).reshape(a_pose.shape[0], -1),
            b_pose=np.asarray(b["em_pose"], dtype=np.float64).reshape(-1, 4),
        )


@dataclass
class _Scan:
    """What the scan of A's templates found: each run's best confirmed state, matching templates, longest run."""

    runs: dict[int, tuple[list[Observation], tuple[tuple[int, int], ...]]] = field(default_factory=dict)
    matched: int = 0
    longest: int = 0


def _scan_runs(cells: LocalViewCells, threshold: float, arrays: _MatchArrays, streak: Streak) -> _Scan:
    """Match A's templates in creation order against B's; return every run's best confirmed state."""
    scan = _Scan()
    run = 0
    for i in range(arrays.a_means.shape[0]):
        u, error, relative = cells.match(arrays.a_templates[i], float(arrays.a_means[i]), limit=threshold)
        if u < 0 or error > threshold:
            streak.reset()
            run += 1
            continue
        scan.matched += 1
        before = len(streak.entries)
        streak.add(_observation(arrays, streak, i, u, error, relative))
        run += len(streak.entries) <= before  # the streak restarted: a new run
        scan.longest = max(scan.longest, len(streak.entries))
        if streak.confirmed and _score(streak.entries) > _score(scan.runs.get(run, ([], ()))[0]):
            scan.runs[run] = (list(streak.entries), streak.pairs())
    return scan


def _observation(arrays: _MatchArrays, streak: Streak, i: int, u: int, error: float, relative: float) -> Observation:
    """Return A's template ``i`` matching B's template ``u`` as an observation of the streak."""
    mine = _experience_for(arrays.a_order, arrays.a_starts, i)
    theirs = _experience_for(arrays.b_order, arrays.b_starts, u)
    exp_a = int(mine[0]) if mine.size else -1
    exp_b = -1
    if theirs.size and exp_a >= 0:
        predicted = streak.predict(arrays.a_pose[exp_a])
        if predicted is None or theirs.size == 1:
            exp_b = int(theirs[0])
        else:
            distances = np.linalg.norm(arrays.b_pose[theirs, :3] - predicted[:3], axis=1)
            exp_b = int(theirs[int(np.argmin(distances))])
    seen = compose(arrays.b_pose[exp_b], np.array([0.0, 0.0, 0.0, relative])) if exp_b >= 0 else np.zeros(4)
    return Observation(
        frame=i,
        stored_template=u,
        stored_experience=exp_b,
        error=float(error),
        relative_rad=float(relative),
        partial_template=i,
        odometry=arrays.a_pose[exp_a] if exp_a >= 0 else np.zeros(4),
        packet=arrays.a_pc[exp_a] if exp_a >= 0 else np.zeros(arrays.a_pc.shape[1]),
        seen=seen,
    )


def _score(entries: list[Observation]) -> tuple[int, float]:
    """A run's rank: the most agreeing templates, then the lowest mean error."""
    return (len(entries), -float(np.mean([e.error for e in entries])) if entries else 0.0)


def _match_of(
    a: Any, a_order: np.ndarray, a_starts: np.ndarray, entries: list[Observation], pairs: tuple[tuple[int, int], ...]
) -> Match:
    """The match of one confirmed run, anchored at its best-matching (latest on ties) template."""
    anchor = min(reversed(entries), key=lambda e: e.error)
    exp_a = int(_experience_for(a_order, a_starts, anchor.partial_template)[0])
    return Match.at_experience(
        a,
        exp_a,
        anchor.stored_template,
        anchor.stored_experience,
        relative_rad=anchor.relative_rad,
        confirmations=len(entries),
        pairs=pairs,
    )


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

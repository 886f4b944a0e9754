"""The offline merge's evidence: miss runs along a map's chain and the probation an online merge would have run."""

from __future__ import annotations

import numpy as np
import pytest

from mapserver.merge.hypotheses import HIT, MISS, UNMAPPED, EvidenceRule
from mapserver.merge.offline_evidence import OfflineEvidence, _longest_miss_run, _probation_window

H, M, U = HIT, MISS, UNMAPPED


def _evidence(probation_run: float, reverse: OfflineEvidence | None = None) -> OfflineEvidence:
    return OfflineEvidence(hit_m=30.0, miss_m=2.0, unmapped_m=0.0, turn_rad=3.0, evidence_m=4.0, miss_weight=2.0,
                           hits=30, misses=2, probation=(20.0, probation_run, 20.0), reverse=reverse)  # fmt: skip


def test_a_miss_run_is_the_miss_metres_between_two_hits_unmapped_trials_neither_adding_nor_breaking() -> None:
    steps = np.array([0.0, 1.0, 1.0, 1.0, 0.5, 2.0, 1.0, 1.0])
    outcomes = np.array([H, M, M, H, M, U, M, H])
    # runs: trials 1–2 (2 m), trials 4–6 (0.5 m + 1 m; the 2 m unmapped between them add nothing)
    assert _longest_miss_run(steps, outcomes == H, outcomes == M) == 2.0
    assert _longest_miss_run(steps, outcomes == H, np.zeros(8, dtype=bool)) == 0.0


def test_the_probation_lasts_its_distance_then_ends_evidence_metres_after_the_newest_hit() -> None:
    rule = EvidenceRule.for_map(1.0, 3.0, 0.5, 4.0, 6.0)
    steps = np.ones(13)  # trials 1 m apart after the anchor, at 1, 2, …, 13 m
    outcomes = np.array([H, H, M, M, M, H, M, M, M, M, M, U, U])
    # hits at 1, 2 and 6 m; past 6 m (probation_m) it ends 4 m (evidence_m) after the newest hit: at 10 m
    metres, run, score = _probation_window(steps, outcomes, 6.0, rule)
    assert (metres, run) == (10.0, 4.0)  # misses 3–5 m (3 m) and 7–10 m (4 m): the window's longest run
    assert score == pytest.approx(3.0 - 2.0 * 7.0)
    metres, run, _ = _probation_window(np.ones(60), np.full(60, H), 6.0, rule)
    assert (metres, run) == (48.0, 0.0)  # matches that never stop: PROBATION_CAP (8) probation distances


def test_an_alignment_stands_only_where_neither_maps_probation_meets_a_run_of_evidence_metres() -> None:
    assert _evidence(3.9).passed  # must still: runs shorter than evidence_m
    assert not _evidence(4.0).passed and "failing views in a row" in _evidence(4.0).reason()
    assert _evidence(1.0, reverse=_evidence(3.9)).passed
    refused = _evidence(1.0, reverse=_evidence(4.5))
    assert not refused.passed and "the other map's chain meets 4.5 m" in refused.reason()

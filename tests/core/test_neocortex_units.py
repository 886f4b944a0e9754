"""Neocortical front-end pieces with hand-computed expectations: LSBH, SP, TM, descriptor and gates."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from core.neocortex.descriptor import MatchGates, best_match, cap_topk, interval_length, overlap_scores
from core.neocortex.lsbh import fuse, lsbh_bits, projection
from core.neocortex.spatial_pooler import SpatialPooler
from core.neocortex.temporal_memory import TemporalMemory, TMConfig


def _bits(indices_1based: list[int], n: int = 16) -> list[int]:
    out = [0] * n
    for i in indices_1based:
        out[i - 1] = 1
    return out


def test_lsbh_reproduces_the_thesis_worked_example() -> None:
    """Thesis §4.2.2 worked example 1: L = 16, p = 8, k = 2; camera, sonar and their OR."""
    cam = torch.tensor([0.9, -1.2, 0.1, -0.8, 2.1, -0.4, 0.7, -1.5])
    son = torch.tensor([0.2, -0.9, 1.5, -1.1, 0.4, -0.2, 0.8, -1.7])
    s_cam, s_son = lsbh_bits(cam, 2), lsbh_bits(son, 2)
    assert s_cam.int().tolist() == _bits([1, 5, 10, 16])
    assert s_son.int().tolist() == _bits([3, 7, 12, 16])
    assert fuse([s_cam, s_son]).int().tolist() == [1, 0, 1, 0, 1, 0, 1, 0, 0, 1, 0, 1, 0, 0, 0, 1]
    assert fuse([s_cam]).equal(s_cam)  # a dropped modality: the other still drives the code


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-5, 5, allow_nan=False), min_size=4, max_size=40), st.integers(1, 10))
def test_lsbh_has_exactly_2k_bits_split_by_rank(values: list[float], k: int) -> None:
    """2k ones; every top-half bit's value ≥ every unset value ≥ every bottom-half bit's value."""
    v = torch.tensor(values, dtype=torch.float64)
    p = v.numel()
    k = min(k, p // 2)
    bits = lsbh_bits(v, k)
    top, bottom = bits[:p], bits[p:]
    assert int(top.sum()) == k and int(bottom.sum()) == k
    assert float(v[top].min()) >= float(v[~top].max())  # k ≤ p/2: both sets are non-empty
    assert float(v[bottom].max()) <= float(v[~bottom].min())


def test_projection_is_seeded_with_unit_columns() -> None:
    a, b, c = projection(30, 8, 42), projection(30, 8, 42), projection(30, 8, 43)
    assert a.equal(b) and not a.equal(c)
    assert torch.allclose(torch.linalg.vector_norm(a, dim=0), torch.ones(8), atol=1e-6)


def _tiny_sp(perm: list[list[float]], active: int = 2) -> SpatialPooler:
    sp = SpatialPooler(6, 4, active, potential_radius=6, potential_pct=1.0, connected=0.5, inc=0.1, dec=0.05)
    sp.potential = torch.ones((4, 6), dtype=torch.bool)
    sp.permanence = torch.tensor(perm, dtype=torch.float32)
    sp.sync_connected()
    return sp


def test_spatial_pooler_overlap_inhibition_and_learning_by_hand() -> None:
    """Connected = perm ≥ 0.5. Input bits {0, 1, 2}: overlaps 3, 1, 2, 0 → winners {0, 2}."""
    sp = _tiny_sp([
        [0.6, 0.6, 0.6, 0.1, 0.1, 0.1],  # 3 connected inputs on
        [0.6, 0.1, 0.1, 0.6, 0.6, 0.6],  # 1
        [0.1, 0.7, 0.5, 0.9, 0.1, 0.1],  # 2 (0.5 is connected)
        [0.4, 0.4, 0.4, 0.6, 0.6, 0.6],  # 0 (0.4 < 0.5)
    ])
    x = torch.tensor([1, 1, 1, 0, 0, 0], dtype=torch.bool)
    assert sp.overlaps(x).tolist() == [3, 1, 2, 0]
    winners = sp.compute(x, learn=True)
    assert winners.tolist() == [0, 2]
    # winners: +0.1 on active inputs, −0.05 on inactive ones; losers unchanged
    assert torch.allclose(sp.permanence[0], torch.tensor([0.7, 0.7, 0.7, 0.05, 0.05, 0.05]))
    assert torch.allclose(sp.permanence[2], torch.tensor([0.2, 0.8, 0.6, 0.85, 0.05, 0.05]))
    assert torch.equal(sp.permanence[1], torch.tensor([0.6, 0.1, 0.1, 0.6, 0.6, 0.6]))
    assert sp.overlaps(x).tolist() == [3, 1, 2, 0]  # column 2's input 0 rose to 0.2, still < 0.5
    for _ in range(3):  # three more wins: 0.2 → 0.5 connects input 0 of column 2
        sp.compute(x, learn=True)
    assert sp.permanence[2, 0].item() == pytest.approx(0.5) and sp.overlaps(x).tolist()[2] == 3


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), inputs=st.integers(1, 200), share=st.floats(0.0, 1.0))
def test_the_cpus_bit_rows_count_the_overlaps_the_float_rows_count(seed: int, inputs: int, share: float) -> None:
    """On the CPU a column's overlap is a popcount of bit rows (any input width, padded to 64); elsewhere a sum
    of float rows. Both give #{i : x_i ∧ perm(c, i) ≥ connected}, counted here directly, and so the same winners
    and the same learning over several steps."""
    def pooler(bits: bool) -> SpatialPooler:
        sp = SpatialPooler(inputs, 24, 5, potential_radius=inputs, potential_pct=0.7, connected=0.5, inc=0.1,
                           dec=0.05, seed=seed)  # fmt: skip
        sp._bits = bits
        sp.sync_connected()
        return sp

    cpu, other = pooler(True), pooler(False)
    rng = np.random.default_rng(seed)
    for _ in range(6):
        x = torch.from_numpy(rng.random(inputs) < share)
        direct = ((cpu.permanence >= 0.5) & x[None, :]).sum(dim=1)
        assert cpu.overlaps(x).tolist() == other.overlaps(x).tolist() == direct.tolist()
        assert torch.equal(cpu.compute(x, learn=True), other.compute(x, learn=True))
        assert torch.equal(cpu.permanence, other.permanence)


def test_spatial_pooler_ties_go_to_the_lower_column_and_zero_overlap_never_wins() -> None:
    sp = _tiny_sp([[0.6, 0.1, 0.1, 0.1, 0.1, 0.1]] * 3 + [[0.1] * 6], active=3)
    x = torch.tensor([1, 0, 0, 0, 0, 0], dtype=torch.bool)
    assert sp.compute(x, learn=False).tolist() == [0, 1, 2]
    sp2 = _tiny_sp([[0.6, 0.1, 0.1, 0.1, 0.1, 0.1]] + [[0.1] * 6] * 3, active=3)
    assert sp2.compute(x, learn=False).tolist() == [0]  # columns without overlap stay inactive


def _tm() -> TemporalMemory:
    return TemporalMemory(TMConfig(columns=32, cells_per_column=4, activation_threshold=3, min_threshold=2,
                                   initial_permanence=0.55, connected_permanence=0.5, max_new_synapse_count=4,
                                   max_synapses_per_segment=8, permanence_increment=0.05, permanence_decrement=0.01))


_COLUMNS = {"A": [0, 1, 2, 3], "B": [4, 5, 6, 7], "C": [8, 9, 10, 11], "D": [12, 13, 14, 15], "X": [20, 21, 22, 23]}
SEQ = {name: torch.tensor(cols) for name, cols in _COLUMNS.items()}


def _present(tm: TemporalMemory, names: str, learn: bool) -> list[tuple[torch.Tensor, torch.Tensor]]:
    return [tm.compute(SEQ[n], learn=learn) for n in names]


def _dense_step(tm: TemporalMemory, columns: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The TM's active cells and its correctly predicted cells by masks over every cell (the oracle)."""
    cfg, g = tm.cfg, tm.segments
    pre, perm = tm.syn_pre[:g], tm.syn_perm[:g]
    pre_act = (pre >= 0) & tm.prev_active[pre.clamp(min=0)]
    seg_active = (pre_act & (perm >= cfg.connected_permanence)).sum(dim=1) >= cfg.activation_threshold
    col_on = torch.zeros(cfg.columns, dtype=torch.bool)
    col_on[columns] = True
    predicted = torch.zeros(tm.cells, dtype=torch.bool)
    predicted[tm.seg_cell[:g][seg_active]] = True
    grid = predicted.view(cfg.columns, cfg.cells_per_column)
    predicted_cols = grid.any(dim=1) & col_on
    correct = (grid & predicted_cols[:, None]).flatten()
    active = correct | (col_on & ~predicted_cols)[:, None].expand(-1, cfg.cells_per_column).flatten()
    return torch.nonzero(active).flatten(), torch.nonzero(correct).flatten()


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 6), st.sampled_from([0, 4096]), st.sampled_from([0.0, 0.02]),
       st.sampled_from([0.01, 0.3]))  # fmt: skip
def test_the_tms_step_by_cell_ids_activates_the_cells_masks_over_every_cell_would(
    seed: int, period: int, rebuild_min: int, punish: float, decrement: float
) -> None:
    """The step through the synapse index (rebuilt every few steps, or never in 30) against masks over every
    segment and cell, learning on and off, with and without punishing matching segments of inactive columns;
    with a decrement of 0.3 synapses die after two misses and full segments overwrite their weakest slots, so
    the index holds slots that no longer point where it says."""
    import dataclasses

    from core.neocortex import temporal_memory

    generator = torch.Generator().manual_seed(seed)
    tm = _tm()
    tm.cfg = dataclasses.replace(tm.cfg, predicted_segment_decrement=punish, permanence_decrement=decrement,
                                 max_synapses_per_segment=8 if decrement < 0.1 else 4)  # fmt: skip
    m = tm.cfg.max_synapses_per_segment
    tm.syn_pre, tm.syn_perm = tm.syn_pre[:, :m], tm.syn_perm[:, :m]
    saved = temporal_memory.INDEX_REBUILD_MIN
    temporal_memory.INDEX_REBUILD_MIN = rebuild_min
    try:
        _drive_against_masks(tm, generator, period)
    finally:
        temporal_memory.INDEX_REBUILD_MIN = saved


def _drive_against_masks(tm: TemporalMemory, generator: torch.Generator, period: int) -> None:
    inputs = [torch.randperm(32, generator=generator)[:4].sort().values for _ in range(period)]
    for step in range(30):  # a repeating sequence (predictions) with a novel input now and then (bursts)
        columns = inputs[step % period] if step % 7 else torch.randperm(32, generator=generator)[:4].sort().values
        active_ref, correct_ref = _dense_step(tm, columns)
        pre_act = tm.synapse_activity()
        pre = tm.syn_pre[: tm.segments]
        assert torch.equal(pre_act, (pre >= 0) & tm.prev_active[pre.clamp(min=0)])
        active, winners = tm.compute(columns, learn=step % 5 != 4)
        assert torch.equal(active, active_ref)
        assert torch.equal(torch.isin(correct_ref, winners), torch.ones(correct_ref.numel(), dtype=torch.bool))
        assert winners.numel() == correct_ref.numel() + int(columns.numel() - torch.unique(correct_ref // 4).numel())


def test_temporal_memory_predicts_a_learnt_sequence_and_bursts_on_a_novel_one() -> None:
    """After A-B-C-D is learnt, A predicts B's columns (one cell each, 4 active cells); X-B bursts (16 cells)."""
    tm = _tm()
    first = _present(tm, "ABCD", learn=True)
    assert [int(a.numel()) for a, _ in first] == [16, 16, 16, 16]  # nothing learnt yet: every column bursts
    for _ in range(3):
        tm.prev_active = torch.zeros(tm.cells, dtype=torch.bool)  # a sequence reset between repetitions
        tm.prev_winners = torch.empty(0, dtype=torch.int64)
        _present(tm, "ABCD", learn=True)
    tm.prev_active = torch.zeros(tm.cells, dtype=torch.bool)
    tm.prev_winners = torch.empty(0, dtype=torch.int64)
    learnt = _present(tm, "ABCD", learn=False)
    assert [int(a.numel()) for a, _ in learnt[1:]] == [4, 4, 4]  # B, C, D predicted: one cell per column
    for (active, winners), cols in zip(learnt[1:], ("B", "C", "D"), strict=True):
        assert sorted({int(c) // 4 for c in active}) == SEQ[cols].tolist()
        assert torch.equal(active, winners)
    novel = _present(tm, "XB", learn=False)
    assert int(novel[1][0].numel()) == 16  # B after X was never seen: it bursts
    again = _present(tm, "AB", learn=False)
    assert int(again[1][0].numel()) == 4 and torch.equal(again[1][0], learnt[1][0])  # same context → same cells


def test_temporal_memory_snapshot_restores_exactly() -> None:
    tm = _tm()
    _present(tm, "ABCDXAB", learn=True)
    copy = _tm()
    copy.load(tm.snapshot())
    a = _present(tm, "CDA", learn=True)
    b = _present(copy, "CDA", learn=True)
    assert all(torch.equal(x[0], y[0]) and torch.equal(x[1], y[1]) for x, y in zip(a, b, strict=True))
    for key, value in tm.snapshot().items():
        assert np.array_equal(value, copy.snapshot()[key]), key


def test_cap_topk_keeps_the_most_frequent_then_the_most_recent() -> None:
    history = [np.array([1, 2, 3]), np.array([2, 3, 4]), np.array([3, 5, 9])]
    # counts: 3→3, 2→2, then 1, 4, 5, 9 once each; recency: 5 and 9 (last step) before 4, then 1
    assert cap_topk(history, 2).tolist() == [2, 3]
    assert cap_topk(history, 4).tolist() == [2, 3, 5, 9]
    assert cap_topk(history, 5).tolist() == [2, 3, 4, 5, 9]
    assert cap_topk([], 3).size == 0


def test_interval_length() -> None:
    assert interval_length(run=1, window=7, theta_rho=3, interval_mode=True) == 3
    assert interval_length(run=5, window=7, theta_rho=3, interval_mode=True) == 5
    assert interval_length(run=12, window=7, theta_rho=3, interval_mode=True) == 7
    assert interval_length(run=1, window=7, theta_rho=3, interval_mode=False) == 7


def _protos(rows: list[list[int]], width: int = 15) -> tuple[np.ndarray, np.ndarray]:
    out = np.full((len(rows), width), -1, dtype=np.int64)
    for i, r in enumerate(rows):
        out[i, : len(r)] = r
    return out, np.array([len(r) for r in rows])


def test_gates_worked_example_and_each_gate_alone() -> None:
    """Thesis worked example: |D| = 15, I = 12 → R = 0.8, accepted (F1 = 24/30 = 0.8 ≥ 0.55)."""
    d = np.arange(15)
    protos, sizes = _protos([[*list(range(12)), 100, 101, 102]])
    match = best_match(d, protos, sizes, MatchGates())
    assert match is not None and match.accepted
    assert (match.index, match.intersection, match.recall, match.f1) == (0, 12, 0.8, 0.8)
    # I = 11 < I_min = 12: refused although R = 11/15 ≥ 0.30
    protos, sizes = _protos([[*list(range(11)), 100, 101, 102, 103]])
    refused = best_match(d, protos, sizes, MatchGates())
    assert refused is not None and not refused.accepted and refused.intersection == 11
    assert best_match(d, protos, sizes, MatchGates(min_intersection=11)).accepted  # must still happen
    # R gate: |D| = 15, I = 12 of a 15-bit prototype passes τ_R = 0.8 but not τ_R = 0.81
    protos, sizes = _protos([[*list(range(12)), 100, 101, 102]])
    assert best_match(d, protos, sizes, MatchGates(tau_r=0.8)).accepted
    assert not best_match(d, protos, sizes, MatchGates(tau_r=0.81)).accepted


def test_f1_gate_refuses_a_dense_prototype_that_recall_accepts() -> None:
    """D ⊂ a 60-bit prototype: R = 1 but F1 = 2·15/(15 + 60) = 0.4 < 0.55; without the gate it is accepted."""
    d = np.arange(15)
    protos, sizes = _protos([list(range(60))], width=60)
    gated = best_match(d, protos, sizes, MatchGates())
    assert gated is not None and gated.recall == 1.0 and gated.f1 == pytest.approx(0.4) and not gated.accepted
    assert best_match(d, protos, sizes, MatchGates(f1_gate=False)).accepted


def test_iou_breaks_recall_ties() -> None:
    """Both prototypes hold all of D (R = 1); the smaller one has the larger IoU (15/15 vs 15/20) and wins."""
    d = np.arange(15)
    protos, sizes = _protos([list(range(20)), list(range(15))], width=20)
    inter, recall, _, iou = overlap_scores(d, protos, sizes)
    assert inter.tolist() == [15, 15] and recall.tolist() == [1.0, 1.0] and iou.tolist() == [0.75, 1.0]
    assert best_match(d, protos, sizes, MatchGates()).index == 1
    assert best_match(d, protos, sizes, MatchGates(iou_tiebreak=False)).index == 0


def test_a_poolers_snapshot_keeps_its_pools_permanences_in_the_masks_order_and_loads_them_back() -> None:
    sp = SpatialPooler(64, 32, 4, potential_radius=16, potential_pct=0.5, connected=0.2, inc=0.1, dec=0.05, seed=3)
    generator = torch.Generator().manual_seed(0)
    sp.permanence = torch.rand((32, 64), generator=generator) * sp.potential  # as learning leaves it
    state = sp.snapshot()
    assert np.array_equal(state["sp_permanence"], sp.permanence[sp.potential].numpy())  # by the boolean mask
    other = SpatialPooler(64, 32, 4, potential_radius=16, potential_pct=0.5, connected=0.2, inc=0.1, dec=0.05, seed=3)
    other.load(state)
    assert torch.equal(other.permanence, sp.permanence)
    sp.potential = sp.potential.clone()
    sp.potential[0] = False  # a pool replaced: its ids found again
    assert sp.snapshot()["sp_permanence"].size == int(sp.potential.sum())


def test_projections_drawn_once_per_seed_are_handed_out_as_independent_copies() -> None:
    from core.neocortex.lsbh import digest, projection_digest

    first = projection(30, 8, 42)
    first += 1.0  # must not reach the next one
    again = projection(30, 8, 42)
    assert torch.allclose(torch.linalg.vector_norm(again, dim=0), torch.ones(8), atol=1e-6)
    assert np.array_equal(projection_digest(30, 8, 42), digest(again))
    assert not np.array_equal(projection_digest(30, 8, 43), digest(again))


def test_pools_drawn_once_per_seed_are_handed_out_as_independent_copies() -> None:
    """Poolers built from one seed start equal; one pooler's learning never reaches the next one built."""
    from core.neocortex.spatial_pooler import initial_pools

    first, first_perm = initial_pools(64, 32, 16, 0.5, 0.2, seed=7)
    first_perm += 1.0  # what learning in place would do to a shared tensor
    first[0, :] = ~first[0, :]
    second, second_perm = initial_pools(64, 32, 16, 0.5, 0.2, seed=7)
    again, again_perm = initial_pools(64, 32, 16, 0.5, 0.2, seed=7)
    assert torch.equal(second, again) and torch.equal(second_perm, again_perm)
    assert not torch.equal(first, second) and float(second_perm.max()) <= 1.0
    assert torch.equal(second_perm > 0, second)  # permanences only on the potential pool
    other, _ = initial_pools(64, 32, 16, 0.5, 0.2, seed=8)
    assert not torch.equal(other, second)

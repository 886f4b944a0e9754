"""VPR Guard (PoseidonSLAM thesis Eqs. 4.11–4.14, worked example 2) and the motion gate."""

from __future__ import annotations

from core.config import Params
from core.gate import EventGate


def test_worked_example_accepts_a_repeated_id() -> None:
    gate = EventGate(Params().replace(vpr_guard=True, vpr_window=26, vpr_min_rep=3, vpr_leak_rate=20))
    decisions = [gate.observe(i) for i in [12, 12, 7, 12, 5, 9, 12]]
    assert decisions[-1] is True  # C_t(12) = 4 ≥ 3
    assert decisions[:2] == [False, False]
    assert [gate.observe(i) for i in [7, 4, 9, 6]] == [False, False, False, False]  # counts 2, 1, 2, 1


def test_leak_forces_an_event_after_l_max_rejections_and_resets() -> None:
    gate = EventGate(Params().replace(vpr_guard=True, vpr_window=26, vpr_min_rep=3, vpr_leak_rate=20))
    decisions = [gate.observe(100 + i) for i in range(45)]  # all distinct: g = 0 always
    accepted = [i for i, d in enumerate(decisions) if d]
    assert accepted == [19, 39]  # q reaches 20 at the 20th and 40th rejection
    assert gate.rejections == 5


def test_guard_off_accepts_everything() -> None:
    gate = EventGate(Params())
    assert all(gate.observe(i) for i in range(10))


def test_motion_gate_is_xy_or_z() -> None:
    gate = EventGate(Params().replace(motion_gate=True, min_event_trans_xy=0.12, min_event_dz=0.05))
    gate.observe(0)
    assert not gate.allows_event(0.05, 0.05, 0.01)
    assert gate.allows_event(0.1, 0.1, 0.0)  # hypot = 0.141
    assert gate.allows_event(0.0, 0.0, -0.06)

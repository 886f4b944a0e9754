"""PC-MLIF network invariants: normalisation, one packet, path integration by the commanded cells, the box."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from core.config import Params
from core.mlif import MlifPoseCells
from core.mlif.network import KernelSpec, MlifNetwork

PARAMS = Params(pc_model="mlif")  # 21 × 21 × 36 heading lattice, one z cell
MOVE_TOLERANCE = 0.15
"""Cells. Path integration itself is exact (linear interpolation of a sum-1 packet moves its mean by exactly the
command); what moves the decoded centre off it is the attractor step, which re-sharpens the interpolated packet
towards a cell and so drags a moving packet back by a fraction of a cell, and the ±3-cell population-vector
decoding. Measured: 0.03 cells after 10 cells of translation, 0.02 after 18 cells of turning; 0.15 is 5× that."""


def settled(updates: int = 30) -> MlifPoseCells:
    cells = MlifPoseCells(PARAMS)
    for _ in range(updates):
        cells.on_odo(0.0, 0.0)
    return cells


def one_packet(activity: np.ndarray) -> bool:
    """Whether the active cells form one 26-connected blob, the lattice rolled to put its peak in the middle."""
    peak = np.unravel_index(int(np.argmax(activity)), activity.shape)
    centred = np.roll(activity, [d // 2 - int(p) for p, d in zip(peak, activity.shape, strict=True)],
                      axis=tuple(range(activity.ndim)))
    _, count = ndimage.label(centred > 0, structure=np.ones((3,) * activity.ndim))
    return count == 1


def test_activity_is_normalised_and_non_negative() -> None:
    cells = settled(5)
    for network in (cells.position, cells.heading):
        a = network.activity.numpy()
        assert a.min() >= 0.0
        assert abs(a.sum() - 1.0) < 1e-12


def test_a_still_packet_stays_one_packet_in_place_and_keeps_firing() -> None:
    cells = settled(60)
    assert one_packet(cells.heading.activity.numpy())
    assert one_packet(cells.position.activity.numpy())
    assert np.abs(cells.best - np.asarray([10.0, 10.0, 18.0])).max() < 1e-9  # symmetric packet: the start cell
    assert cells.heading.spikes > 0  # the peak neurons fire every update or so (NEURON_STEPS ≈ their period)
    assert 5 < int((cells.heading.activity.numpy() > 0).sum()) < 200  # a packet, neither one cell nor a smear


def test_translation_moves_the_packet_by_the_commanded_cells() -> None:
    cells = settled()
    start = cells.best.copy()
    for _ in range(20):
        cells.on_odo(0.5 * PARAMS.pc_cell_x_size, 0.0)
    # heading layer 18 of 36 = π: 10 cells along −x
    assert abs((start[0] - cells.best[0]) % 21 - 10.0) < MOVE_TOLERANCE  # 10 → 0: at the face, wrapping
    assert abs(cells.best[1] - start[1]) < MOVE_TOLERANCE
    assert one_packet(cells.position.activity.numpy())
    assert one_packet(cells.heading.activity.numpy())


def test_rotation_moves_theta_and_then_translation_follows_the_new_heading() -> None:
    cells = settled()
    start = cells.best.copy()
    for _ in range(9):
        cells.on_odo(0.0, 2.0 * math.pi / 36)
    assert abs((cells.best[2] - start[2]) % 36 - 9.0) < MOVE_TOLERANCE  # θ moved 9 cells (now π/2 + π = 3π/2)
    assert np.abs(cells.best[:2] - start[:2]).max() < MOVE_TOLERANCE  # turning on the spot: x, y stay
    for _ in range(6):
        cells.on_odo(1.0 * PARAMS.pc_cell_x_size, 0.0)
    assert abs((start[1] - cells.best[1]) - 6.0) < 2 * MOVE_TOLERANCE  # heading 27 of 36 = 3π/2: along −y
    assert abs(cells.best[0] - start[0]) < 2 * MOVE_TOLERANCE


def test_depth_moves_the_position_network_in_z() -> None:
    params = Params(pc_model="mlif", pc_dim_xy=15, pc_dim_th=12, pc_dim_z=11)
    cells = MlifPoseCells(params)
    assert cells.rank == 4
    for _ in range(20):
        cells.on_odo(0.0, 0.0)
    start = cells.best.copy()
    for _ in range(8):
        cells.on_odo(0.0, 0.0, 0.5 * params.pc_cell_z_size)
    assert abs(cells.best[2] - start[2] - 4.0) < MOVE_TOLERANCE
    assert np.abs(cells.best[[0, 1, 3]] - start[[0, 1, 3]]).max() < MOVE_TOLERANCE


def test_the_box_computes_what_the_whole_lattice_computes(monkeypatch: pytest.MonkeyPatch) -> None:
    def run(full: bool) -> MlifNetwork:
        net = MlifNetwork((31, 31, 24), KernelSpec(7, 1.0, 5, 2.0))
        if full:
            monkeypatch.setattr(net, "box", lambda: [np.arange(d) for d in net.shape])
        for k in range(12):
            net.attract()
            net.shift((0.7, -0.3, 0.4 if k % 2 else 0.0))
        return net

    boxed, whole = run(False), run(True)
    assert all(len(run_) < d for run_, d in zip(boxed.box(), boxed.shape, strict=True))  # smaller than the lattice
    for a, b in ((boxed.activity, whole.activity), (boxed.state.v, whole.state.v), (boxed.state.x, whole.state.x)):
        assert torch.equal(a, b)


def test_a_familiar_view_pulls_the_packet_back_and_a_young_one_does_not() -> None:
    """Two views linked at x 10, then 6 cells of travel, then the views again (alternating, so neither saturates).

    Measured: the packet holds at x 4 for 6 injections, then jumps to the linked place (the CAN lattice jumps
    after 1); with templates too young to inject it never moves.
    """

    def after_revisit(template_count: int) -> np.ndarray:
        params = PARAMS.replace(openratslam_parts="none")  # the age rule as written: template < count − 10
        cells = MlifPoseCells(params)
        for _ in range(20):
            cells.on_odo(0.0, 0.0)
        cells.on_view_template(0, 0.0, 1, created=True)  # both linked here (x 10)
        cells.on_view_template(1, 0.0, 2, created=True)
        for _ in range(6):
            cells.on_odo(1.0, 0.0)  # 6 cells along −x
        assert abs(cells.best[0] - 4.0) < MOVE_TOLERANCE
        for k in range(12):
            cells.on_view_template(k % 2, 0.0, template_count, created=False)
            cells.on_odo(0.0, 0.0)
        return cells.best

    assert abs(after_revisit(template_count=20)[0] - 10.0) < MOVE_TOLERANCE  # old enough: back at the link
    assert abs(after_revisit(template_count=5)[0] - 4.0) < MOVE_TOLERANCE  # too young: stays where it went

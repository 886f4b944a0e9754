"""NeuroSLAM's grid-cell and head-direction networks against the paper's numbers and a dense reference.

The settling figures (171 active cells, peak 0.0247; 32–37 cells, peak ≈ 0.067, a drift of about −0.5 cell)
come from an independent numpy check recorded in ``shared/notes/neuroslam.md`` §1.3 and §2.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.neuroslam import (
    Codes,
    ConjunctivePoseCells,
    GridCellParams,
    HeadDirectionParams,
    Kernel,
    WrappedAttractor,
    injection_energy,
)


def grid_network(params: GridCellParams | None = None) -> WrappedAttractor:
    p = params or GridCellParams()
    return WrappedAttractor(p.dims, Kernel.gaussian((7, 7, 7), (1.5,) * 3), Kernel.gaussian((5, 5, 5), (2.0,) * 3),
                            p.global_inhibition, p.window)


def head_network() -> WrappedAttractor:
    p = HeadDirectionParams()
    return WrappedAttractor(p.dims, Kernel.gaussian((8, 8), (1.9, 1.9)), Kernel.gaussian((5, 5), (3.0, 3.0)),
                            p.global_inhibition, p.window)


def dense_filter(activity: np.ndarray, kernel: Kernel) -> np.ndarray:
    """The wrapped N-D convolution with the kernel's full product, one roll per kernel cell."""
    out = np.zeros_like(activity)
    for combo in itertools.product(*[zip(t.offsets, t.weights, strict=True) for t in kernel.axes]):
        weight = math.prod(w for _, w in combo)
        out += weight * np.roll(activity, tuple(o for o, _ in combo), axis=tuple(range(activity.ndim)))
    return out


def dense_step(net: WrappedAttractor, activity: np.ndarray) -> np.ndarray:
    excited = dense_filter(activity, net.excite)
    clamped = np.maximum(excited - dense_filter(excited, net.inhibit) - net.global_inhibition, 0.0)
    return clamped / clamped.sum()


def test_kernels_cover_the_papers_offsets_and_sum_to_one() -> None:
    head = Kernel.gaussian((8, 8), (1.9, 1.9))
    assert head.axes[0].offsets == (-4, -3, -2, -1, 0, 1, 2, 3)
    assert sum(head.axes[0].weights) == pytest.approx(1.0, abs=1e-15)
    grid = Kernel.gaussian((7, 7, 7), (1.5,) * 3)
    assert grid.axes[2].offsets == (-3, -2, -1, 0, 1, 2, 3)
    # e(0)/e(1) = exp(1/(2σ²)) for σ = 1.5
    assert grid.axes[0].weights[3] / grid.axes[0].weights[4] == pytest.approx(math.exp(1 / 4.5))


@pytest.mark.parametrize("start", [(18, 18, 18), (35, 0, 17)])
def test_grid_packet_settles_as_the_notes_measured(start: tuple[int, int, int]) -> None:
    net = grid_network()
    net.set_single(start)
    for _ in range(5):
        net.step_attractor()
    assert np.count_nonzero(net.activity) == 171
    assert net.activity.max() == pytest.approx(0.0247, abs=2e-4)
    np.testing.assert_allclose(net.decode(), start, atol=1e-9)  # the centre does not move, across edges too


def test_head_packet_settles_and_drifts_half_a_cell_as_the_notes_measured() -> None:
    net = head_network()
    net.set_single((0, 10))
    for _ in range(100):
        net.step_attractor()
    assert 32 <= np.count_nonzero(net.activity) <= 37
    assert net.activity.max() == pytest.approx(0.067, abs=1e-3)
    yaw, height = net.decode()
    assert yaw == pytest.approx(36 - 0.5, abs=0.05)  # the even 8-cell kernel pulls it back across the edge
    assert height == pytest.approx(10 - 0.5, abs=0.05)


def two_packets(dims: tuple[int, ...]) -> np.ndarray:
    """Activity in two places half a lattice apart: the box covers whole axes and wraps."""
    rng = np.random.default_rng(4)
    activity = np.zeros(dims)
    for centre in ([3] * len(dims), [d // 2 + 3 for d in dims]):
        for _ in range(20):
            cell = tuple((c + int(o)) % d for c, o, d in zip(centre, rng.integers(-2, 3, len(dims)), dims, strict=True))
            activity[cell] += rng.random()
    return activity / activity.sum()


@pytest.mark.parametrize("make", [grid_network, head_network])
def test_attractor_step_equals_the_dense_wrapped_convolution(make: object) -> None:
    net = make()  # type: ignore[operator]
    for activity in (two_packets(net.dims), dense_step(net, two_packets(net.dims))):
        expected = dense_step(net, activity)
        net.activity = activity.copy()
        net.step_attractor()
        np.testing.assert_allclose(net.activity, expected, rtol=0, atol=1e-15)


def test_one_packet_step_equals_the_dense_convolution_near_an_edge() -> None:
    net = grid_network()
    net.set_single((0, 35, 1))
    net.step_attractor()
    expected = dense_step(net, net.activity)
    net.step_attractor()
    np.testing.assert_allclose(net.activity, expected, rtol=0, atol=1e-15)


@settings(max_examples=40, deadline=None)
@given(st.tuples(*[st.floats(-40.0, 40.0, allow_nan=False)] * 3))
def test_shift_is_the_exact_linear_interpolation(shift: tuple[float, float, float]) -> None:
    net = grid_network()
    net.set_single((5, 30, 18))
    net.step_attractor()
    before = net.activity.copy()
    net.shift(shift)
    expected = before
    for axis, s in enumerate(shift):
        whole, frac = math.floor(s), s - math.floor(s)
        expected = (1 - frac) * np.roll(expected, whole, axis=axis) + frac * np.roll(expected, whole + 1, axis=axis)
    np.testing.assert_allclose(net.activity, expected, rtol=0, atol=1e-15)
    assert net.activity.sum() == pytest.approx(1.0, abs=1e-12)


def test_integer_shift_moves_the_decoded_centre_by_exactly_that() -> None:
    net = grid_network()
    net.set_single((18, 18, 18))
    for _ in range(5):
        net.step_attractor()
    net.shift((3.0, -20.0, 19.0))
    np.testing.assert_allclose(net.decode(), [21.0, 34.0, 1.0], atol=1e-9)


def test_driving_moves_the_grid_packet_along_the_decoded_heading() -> None:
    cells = ConjunctivePoseCells()
    x0, y0, z0 = cells.codes.grid
    for _ in range(10):
        cells.step(0.5, 0.0, 0.0)  # head packet at yaw cell ~0: heading east
    x, y, _ = cells.codes.grid
    assert x - x0 == pytest.approx(5.0, abs=0.25)
    assert abs(y - y0) < 0.25
    quarter = (math.pi / 2) / 5
    for _ in range(5):
        cells.step(0.0, quarter, 0.0)  # turn left 90° in place: 9 yaw cells
    assert cells.yaw_rad == pytest.approx(math.pi / 2, abs=math.radians(6))
    x1, y1, _ = cells.codes.grid
    height1 = cells.codes.head[1]
    for _ in range(10):
        cells.step(0.5, 0.0, 0.2)  # north, climbing 2 m
    x2, y2, z2 = cells.codes.grid
    assert y2 - y1 == pytest.approx(5.0, abs=0.5)
    assert abs(x2 - x1) < 0.5
    # Both packets follow the climb; each fractional shift is partly pulled back by the next settling (~5 %).
    assert 1.8 < z2 - z0 <= 2.0
    assert 1.6 < (cells.codes.head[1] - height1) % 36 <= 2.0


def test_injection_energy_saturates_as_openratslam() -> None:
    assert injection_energy(0.1, 0.0) == pytest.approx(0.1 * 29 / 30)
    assert injection_energy(0.1, 1.0) == pytest.approx(0.1 * (30 - math.exp(1.2)) / 30)
    assert injection_energy(0.1, math.log(30) / 1.2 + 1e-9) == 0.0


def test_a_familiar_view_pulls_the_packets_and_a_worn_one_does_not() -> None:
    strong = GridCellParams(inject_energy=0.5)
    target = Codes(grid=(8.0, 8.0, 8.0), head=(20.0, 3.0))
    pulled, worn = ConjunctivePoseCells(strong), ConjunctivePoseCells(strong)
    for _ in range(30):
        pulled.calibrate(target, decay=0.0)
        pulled.step(0.0, 0.0, 0.0)
        worn.calibrate(target, decay=3.0)  # e^{3.6} > 30: no energy
        worn.step(0.0, 0.0, 0.0)
    np.testing.assert_allclose(pulled.codes.grid, target.grid, atol=0.3)
    np.testing.assert_allclose(worn.codes.grid, (18.0, 18.0, 18.0), atol=1e-9)


def test_snapshot_restores_bit_for_bit_and_runs_on_identically() -> None:
    first = ConjunctivePoseCells()
    for i in range(7):
        first.step(0.3, 0.05 * i, 0.02)
    second = ConjunctivePoseCells.restore(first.snapshot())
    for cells in (first, second):
        cells.step(0.4, -0.1, 0.0)
    assert first.grid.activity.tobytes() == second.grid.activity.tobytes()
    assert first.head.activity.tobytes() == second.head.activity.tobytes()
    assert first.codes == second.codes
    with pytest.raises(ValueError, match="sizes differ"):
        ConjunctivePoseCells.restore(first.snapshot(), GridCellParams(dims=(20, 20, 20)))


def test_code_distance_wraps_on_every_axis() -> None:
    cells = ConjunctivePoseCells()
    a = Codes(grid=(0.5, 0.0, 35.0), head=(35.0, 0.0))
    b = Codes(grid=(35.5, 3.0, 1.0), head=(1.0, 4.0))
    assert cells.code_distance(a, b) == pytest.approx(math.sqrt(1 + 9 + 4 + 4 + 16))

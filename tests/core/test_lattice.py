"""Wrap-around invariants (hypothesis): wrapped lattice distances, trips around the torus (angles: test_angles)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.lattice import circulant_kernel, gaussian_kernel_1d, wrapped_delta, wrapped_distance
from core.posecells import PoseCellNetwork
from tests.core.conftest import departing

dims = st.integers(2, 40)


@given(dim=dims, a=st.floats(0, 40), b=st.floats(0, 40), k=st.integers(-5, 5))
def test_wrapped_delta_is_symmetric_bounded_and_periodic(dim: int, a: float, b: float, k: int) -> None:
    d = float(wrapped_delta(a, b, dim))
    assert 0.0 <= d <= dim / 2 + 1e-9
    assert float(wrapped_delta(b, a, dim)) == pytest.approx(d, abs=1e-9)
    assert float(wrapped_delta(a + k * dim, b, dim)) == pytest.approx(d, abs=1e-9)
    assert d <= abs(a - b) + 1e-9


@given(
    a=st.lists(st.floats(0, 30), min_size=3, max_size=3),
    b=st.lists(st.floats(0, 30), min_size=3, max_size=3),
    c=st.lists(st.floats(0, 30), min_size=3, max_size=3),
)
def test_wrapped_distance_is_a_metric_on_the_torus(a: list[float], b: list[float], c: list[float]) -> None:
    shape = np.array([11.0, 11.0, 36.0])
    ab = float(wrapped_distance(a, b, shape))
    assert ab == pytest.approx(float(wrapped_distance(b, a, shape)), abs=1e-9)
    assert float(wrapped_distance(a, a, shape)) == pytest.approx(0.0, abs=1e-12)
    assert ab <= float(wrapped_distance(a, c, shape)) + float(wrapped_distance(c, b, shape)) + 1e-9
    assert ab <= math.sqrt(float(np.sum((shape / 2) ** 2))) + 1e-9


def test_wrapped_distance_by_hand() -> None:
    # x: |1 − 10| = 9 → 11 − 9 = 2; y: 0; th: |35 − 1| = 34 → 36 − 34 = 2
    assert float(wrapped_distance([1.0, 4.0, 35.0], [10.0, 4.0, 1.0], [11, 11, 36])) == pytest.approx(math.sqrt(8))


@given(dim=st.integers(1, 12), size=st.sampled_from([1, 3, 5, 7, 9]), var=st.floats(0.5, 3.0))
def test_circulant_kernel_conserves_mass_and_is_circulant(dim: int, size: int, var: float) -> None:
    matrix = circulant_kernel(dim, size, var)
    assert matrix.sum(axis=0) == pytest.approx(np.ones(dim))  # every cell spreads all of its energy
    assert matrix.sum(axis=1) == pytest.approx(np.ones(dim))
    assert np.allclose(np.roll(np.roll(matrix, 1, axis=0), 1, axis=1), matrix)
    assert gaussian_kernel_1d(size, var).sum() == pytest.approx(1.0)


def _random_net(seed: int, **changes: object) -> PoseCellNetwork:
    net = PoseCellNetwork(departing().replace(**changes))
    net.activity = np.random.default_rng(seed).random(net.shape)
    return net


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 1000), laps=st.integers(-2, 2))
def test_a_trip_once_around_the_torus_returns_every_axis_aligned_layer(seed: int, laps: int) -> None:
    """Moving by a whole number of lattice lengths is a no-op on the 0°, 90°, 180°, 270° layers."""
    net = _random_net(seed, pc_dim_xy=9, pc_dim_th=8, pc_cell_x_size=0.5)
    before = net.activity.copy()
    net.path_integrate(forward_m=laps * 9 * 0.5, dyaw_rad=0.0)
    for layer in (0, 2, 4, 6):
        assert np.array_equal(net.activity[:, :, layer], before[:, :, layer])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 1000), turns=st.integers(-3, 3), dz_laps=st.integers(-2, 2))
def test_a_full_turn_and_a_full_climb_return_the_activity(seed: int, turns: int, dz_laps: int) -> None:
    net = _random_net(seed, pc_dim_xy=7, pc_dim_z=5, pc_dim_th=8, pc_cell_z_size=0.2)
    before = net.activity.copy()
    net.path_integrate(forward_m=0.0, dyaw_rad=turns * 2 * math.pi, dz_m=dz_laps * 5 * 0.2)
    assert np.allclose(net.activity, before, atol=1e-12, rtol=0)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 1000), cells=st.integers(-20, 20), layer=st.sampled_from([0, 2, 4, 6]))
def test_there_and_back_along_a_layer_is_the_identity(seed: int, cells: int, layer: int) -> None:
    net = _random_net(seed, pc_dim_xy=9, pc_dim_z=4, pc_dim_th=8, pc_cell_x_size=1.0)
    before = net.activity.copy()
    net.path_integrate(forward_m=float(cells), dyaw_rad=0.0)
    net.path_integrate(forward_m=float(-cells), dyaw_rad=0.0)
    assert np.array_equal(net.activity[..., layer], before[..., layer])

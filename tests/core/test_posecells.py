"""Pose-cell dynamics, path integration across every face, injection saturation (hand-computed).

Every test runs on both paths of :mod:`core.posecells`: the numpy reference and the compiled kernels.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from core import _posecell_kernel as kernels
from core.posecells import PoseCellNetwork
from tests.core.conftest import departing

ONE_PATH = [HealthCheck.function_scoped_fixture]  # the path fixture holds for every example of a test


@pytest.fixture(autouse=True, params=["reference", "compiled"])
def path(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Run the test on the numpy reference path, then on the compiled kernels."""
    if request.param == "compiled":
        kernels.load_compiled()
    monkeypatch.setattr(kernels, "_use_compiled", request.param == "compiled")
    return str(request.param)


def _net(**changes: object) -> PoseCellNetwork:
    return PoseCellNetwork(departing().replace(**changes))


def _single(net: PoseCellNetwork, cell: tuple[int, ...]) -> None:
    net.activity[...] = 0.0
    net.activity[cell] = 1.0


@pytest.mark.parametrize(
    ("layer", "axis", "start", "cells", "expected"),
    [
        (0, 0, 2, 3.0, 5),  # θ=0 moves +x
        (0, 0, 19, 3.0, 1),  # crosses the +x face: 19+3 = 22 ≡ 1 (mod 21)
        (9, 1, 20, 2.0, 1),  # θ=90° (layer 9 of 36) moves +y across the +y face
        (18, 0, 1, 3.0, 19),  # θ=180° moves −x across the −x face: 1−3 ≡ 19
        (27, 1, 0, 1.0, 20),  # θ=270° moves −y across the −y face
    ],
)
def test_packet_moves_v_dt_over_cell_size_cells(layer: int, axis: int, start: int, cells: float, expected: int) -> None:
    net = _net(pc_dim_xy=21, pc_dim_th=36, pc_cell_x_size=0.5)
    cell = [10, 10, layer]
    cell[axis] = start
    _single(net, tuple(cell))
    net.path_integrate(forward_m=cells * 0.5, dyaw_rad=0.0)
    moved = np.unravel_index(int(np.argmax(net.activity)), net.shape)
    want = list(cell)
    want[axis] = expected
    assert tuple(int(v) for v in moved) == tuple(want)
    assert net.activity.max() == pytest.approx(1.0, abs=1e-12)


def test_fractional_shift_splits_mass_bilinearly() -> None:
    net = _net(pc_dim_xy=21, pc_dim_th=36, pc_cell_x_size=1.0)
    _single(net, (20, 4, 0))
    net.path_integrate(forward_m=2.25, dyaw_rad=0.0)  # 2.25 cells along +x from x=20: 22.25 ≡ 1.25
    assert net.activity[1, 4, 0] == pytest.approx(0.75)
    assert net.activity[2, 4, 0] == pytest.approx(0.25)
    assert net.activity.sum() == pytest.approx(1.0)


def test_diagonal_layer_uses_cos_and_sin() -> None:
    net = _net(pc_dim_xy=21, pc_dim_th=8, pc_cell_x_size=1.0)
    _single(net, (10, 10, 1))  # θ = 45°
    net.path_integrate(forward_m=math.sqrt(2.0), dyaw_rad=0.0)  # one cell in x and in y
    assert net.activity[11, 11, 1] == pytest.approx(1.0)


@pytest.mark.parametrize(("start", "dyaw_cells", "expected"), [(3, 2.0, 5), (35, 2.0, 1), (0, -1.0, 35)])
def test_heading_shift_wraps(start: int, dyaw_cells: float, expected: int) -> None:
    net = _net(pc_dim_xy=11, pc_dim_th=36)
    _single(net, (5, 5, start))
    net.path_integrate(forward_m=0.0, dyaw_rad=dyaw_cells * 2 * math.pi / 36)
    assert net.activity[5, 5, expected] == pytest.approx(1.0)


@pytest.mark.parametrize(("start", "dz", "expected"), [(3, 0.2, 5), (14, 0.3, 2), (0, -0.1, 14)])
def test_z_moves_dz_over_cell_z_size_across_faces(start: int, dz: float, expected: int) -> None:
    net = _net(pc_dim_xy=15, pc_dim_z=15, pc_dim_th=8, pc_cell_x_size=0.1, pc_cell_z_size=0.1)
    assert net.shape == (15, 15, 15, 8)
    _single(net, (7, 7, start, 2))
    net.path_integrate(forward_m=0.0, dyaw_rad=0.0, dz_m=dz)
    assert net.activity[7, 7, expected, 2] == pytest.approx(1.0)


def test_attractor_step_normalises_and_keeps_the_packet_centre() -> None:
    net = _net(pc_dim_xy=21, pc_dim_th=36)
    _single(net, (4, 17, 30))
    net.step_attractor()
    assert net.activity.sum() == pytest.approx(1.0)
    assert net.activity.min() >= 0.0
    assert np.unravel_index(int(np.argmax(net.activity)), net.shape) == (4, 17, 30)
    best = net.decode()
    assert best == pytest.approx([4.0, 17.0, 30.0], abs=1e-9)


def _direct_spread(src: np.ndarray, size: int, var: float) -> np.ndarray:
    """OpenRatSLAM's cell-by-cell wrapped spread through the ``size``-cube Gaussian (σ = var), by np.roll."""
    offs = np.arange(size) - size // 2
    w = np.exp(-(offs[:, None, None] ** 2 + offs[None, :, None] ** 2 + offs[None, None, :] ** 2) / (2 * var * var))
    w /= w.sum()
    out = np.zeros_like(src)
    for a in range(size):
        for b in range(size):
            for g in range(size):
                out += w[a, b, g] * np.roll(src, (offs[a], offs[b], offs[g]), axis=(0, 1, 2))
    return out


def test_excite_equals_direct_wrapped_convolution() -> None:
    """The FFT path equals OpenRatSLAM's cell-by-cell spread (independent direct sum)."""
    p = departing().replace(pc_dim_xy=9, pc_dim_th=10, pc_global_inhib=0.0)
    net = PoseCellNetwork(p)
    rng = np.random.default_rng(1)
    cells = rng.random(net.shape)
    cells /= cells.sum()
    net.activity = cells.copy()
    net.step_attractor()

    excited = _direct_spread(cells, 7, 1.0)
    inhibited = excited - _direct_spread(excited, 5, 2.0)
    inhibited = np.maximum(inhibited, 0.0)
    inhibited /= inhibited.sum()
    assert np.allclose(net.activity, inhibited, atol=1e-12)


def test_decode_is_the_circular_mean_of_a_two_cell_packet() -> None:
    net = _net(pc_dim_xy=21, pc_dim_th=36)
    net.activity[...] = 0.0
    net.activity[20, 5, 0] = 0.5  # straddles the x face
    net.activity[0, 5, 0] = 0.5
    best = net.decode()
    assert best[0] == pytest.approx(20.5, abs=1e-9)
    assert best[1] == pytest.approx(5.0, abs=1e-9)


def test_injection_saturation_sequence() -> None:
    """OpenRatSLAM: energy = δ/30·(30 − e^{1.2·decay}); decay += vt_active_decay per repeat, −restore per frame."""
    delta = 0.1
    net = _net(pc_dim_xy=11, pc_dim_th=36, pc_vt_inject_energy=delta, vt_active_decay=1.0, pc_vt_restore=0.05,
               vt_min_inject_age=0)
    net.add_link(0, np.array([3.0, 4.0, 5.0]))
    net.add_link(1, np.array([8.0, 8.0, 8.0]))
    injected = []
    for template in [0, 0, 0, 0, 1, 1, 1]:
        net.activity[...] = 0.0
        net.on_view_template(template, 0.0, template_count=2, created=False)
        injected.append(float(net.activity[3, 4, 5]))
    e = delta / 30.0
    assert injected[0] == pytest.approx(e * (30 - math.exp(1.2 * 1.0)))  # first sighting: decay 1.0
    assert injected[1] == pytest.approx(e * (30 - math.exp(1.2 * 2.0)))  # repeat: 1.0 + 1.0
    assert injected[2] == 0.0  # 1.95 + 1.0 = 2.95 → e^{3.54} > 30: saturated
    assert injected[3] == 0.0
    decay = net.snapshot()["pc_link_decay"]
    # template 0 decay: 3.85 after the 4th repeat, then 3 frames of −0.05 while template 1 is seen
    assert decay[0] == pytest.approx(3.85 - 0.05 * 3)


def test_young_templates_do_not_inject() -> None:
    net = _net(pc_dim_xy=11, pc_dim_th=36, vt_min_inject_age=10)
    net.add_link(0, np.array([3.0, 4.0, 5.0]))
    net.activity[...] = 0.0
    net.on_view_template(0, 0.0, template_count=10, created=False)  # 0 < 10 − 10 is false
    assert net.activity.sum() == 0.0
    net.on_view_template(0, 0.0, template_count=11, created=False)
    assert net.activity[3, 4, 5] > 0.0


def test_relative_rad_offsets_the_injected_heading() -> None:
    net = _net(pc_dim_xy=11, pc_dim_th=36, vt_min_inject_age=0)
    net.add_link(0, np.array([3.0, 4.0, 34.0]))
    net.activity[...] = 0.0
    net.on_view_template(0, 2 * (2 * math.pi / 36), template_count=1, created=False)  # +2 heading cells
    assert net.activity[3, 4, 0] > 0.0  # 34 + 2 ≡ 0


def test_new_template_links_to_the_packet_centre() -> None:
    net = _net(pc_dim_xy=11, pc_dim_th=36)
    net.on_view_template(0, 0.0, template_count=1, created=True)
    snap = net.snapshot()
    assert snap["pc_link_coords"][0] == pytest.approx([5.0, 5.0, 18.0])
    assert snap["pc_link_decay"][0] == pytest.approx(1.0)


@settings(max_examples=40, deadline=None, suppress_health_check=ONE_PATH)
@given(
    forward=st.floats(-5.0, 5.0),
    dyaw=st.floats(-1.0, 1.0),
    seed=st.integers(0, 1000),
)
def test_path_integration_conserves_activity(forward: float, dyaw: float, seed: int) -> None:
    net = _net(pc_dim_xy=11, pc_dim_th=12)
    rng = np.random.default_rng(seed)
    net.activity = rng.random(net.shape)
    total = net.activity.sum()
    net.path_integrate(forward, dyaw)
    assert net.activity.sum() == pytest.approx(total, rel=1e-12)
    assert net.activity.min() >= 0.0


@settings(max_examples=40, deadline=None, suppress_health_check=ONE_PATH)
@given(seed=st.integers(0, 10_000), steps=st.integers(1, 4))
def test_attractor_output_is_a_distribution(seed: int, steps: int) -> None:
    net = _net(pc_dim_xy=11, pc_dim_th=12)
    rng = np.random.default_rng(seed)
    net.activity = rng.random(net.shape) ** 8
    for _ in range(steps):
        net.step_attractor()
    assert net.activity.sum() == pytest.approx(1.0, abs=1e-12)
    assert net.activity.min() >= 0.0


@settings(max_examples=40, deadline=None, suppress_health_check=ONE_PATH)
@given(shift=st.integers(-40, 40), seed=st.integers(0, 100))
def test_integer_translation_is_invertible(shift: int, seed: int) -> None:
    """On the axis-aligned heading layers (0°, 90°, 180°, 270°) an integer move is an exact roll."""
    net = _net(pc_dim_xy=11, pc_dim_th=12, pc_cell_x_size=1.0)
    rng = np.random.default_rng(seed)
    net.activity = rng.random(net.shape)
    before = net.activity.copy()
    net.path_integrate(float(shift), 0.0)
    moved = net.activity.copy()
    net.path_integrate(float(-shift), 0.0)
    for layer, axis, sign in [(0, 0, 1), (3, 1, 1), (6, 0, -1), (9, 1, -1)]:
        assert np.array_equal(moved[:, :, layer], np.roll(before[:, :, layer], sign * shift, axis=axis))
        assert np.array_equal(net.activity[:, :, layer], before[:, :, layer])


@pytest.mark.parametrize(
    ("axis", "layer", "start", "expected"),
    [(0, 0, 13, 1), (0, 4, 1, 13), (1, 2, 14, 2), (1, 6, 0, 12)],  # 8 heading layers: 0°, 180°, 90°, 270°
)
def test_4dof_packet_crosses_every_horizontal_face(axis: int, layer: int, start: int, expected: int) -> None:
    """On the (x, y, z, ψ) lattice the packet moves v·dt/pc_cell_x_size = 3 cells along its layer's heading."""
    net = _net(pc_dim_xy=15, pc_dim_z=15, pc_dim_th=8, pc_cell_x_size=0.1, pc_cell_z_size=0.1)
    cell = [7, 7, 5, layer]
    cell[axis] = start
    _single(net, tuple(cell))
    speed, dt = 0.6, 0.5  # 0.3 m = 3 cells
    net.path_integrate(forward_m=speed * dt, dyaw_rad=0.0)
    want = list(cell)
    want[axis] = expected
    assert net.activity[tuple(want)] == pytest.approx(1.0)


def test_on_odo_decodes_the_packet_v_dt_over_cell_size_further() -> None:
    """The whole on_odo update (attractor step, path integration, decoding) on a one-cell packet.

    A narrow excitation (σ = 0.1 cell) leaves the packet in one cell (its neighbours are inhibited
    to zero), so its decoded centre moves exactly v·dt/pc_cell_x_size cells.
    """
    net = _net(pc_dim_xy=21, pc_dim_th=36, pc_cell_x_size=0.05, pc_w_e_var=0.1)
    _single(net, (19, 10, 9))  # layer 9 = 90°: moves along +y
    best = net.on_odo(forward_m=0.3 * 0.5, dyaw_rad=0.0)  # v = 0.3 m/s for dt = 0.5 s: 0.15 m = 3 cells
    assert best == pytest.approx([19.0, 13.0, 9.0], abs=1e-9)
    best = net.on_odo(forward_m=0.0, dyaw_rad=-10 * 2 * math.pi / 36)  # −10 heading cells: 9 → 35
    assert best == pytest.approx([19.0, 13.0, 35.0], abs=1e-9)


def test_decode_takes_the_first_peak_in_openratslam_scan_order() -> None:
    """Two equal maxima far apart: OpenRatSLAM scans θ outermost, so the lower θ wins, not the lower x."""
    net = _net(pc_dim_xy=21, pc_dim_th=36)
    net.activity[...] = 0.0
    net.activity[8, 5, 3] = 0.5
    net.activity[1, 5, 20] = 0.5
    assert net.decode() == pytest.approx([8.0, 5.0, 3.0], abs=1e-9)


def test_heading_offset_is_kept_until_the_next_injection() -> None:
    """OpenRatSLAM sets vt_delta_pc_th only when a template injects energy."""
    th = 36
    net = _net(pc_dim_xy=11, pc_dim_th=th, vt_min_inject_age=0, pc_vt_restore=0.0)
    net.add_link(0, np.array([3.0, 4.0, 5.0]))
    net.add_link(1, np.array([6.0, 6.0, 6.0]))
    rad = 3 * 2 * math.pi / th
    net.on_view_template(0, rad, template_count=2, created=False)  # injects: offset = 3 cells
    assert net.vt_delta_th == pytest.approx(3.0)
    net.on_view_template(0, rad, template_count=2, created=False)  # repeat: decay 2.0, e^{2.4} < 30, injects
    assert net.vt_delta_th == pytest.approx(3.0)
    net.on_view_template(0, -rad, template_count=2, created=False)  # decay 3.0: e^{3.6} > 30, nothing injected
    assert net.activity.sum() > 0 and net.vt_delta_th == pytest.approx(3.0)  # the offset stays
    net.on_view_template(2, -rad, template_count=3, created=True)  # a new template injects nothing
    assert net.vt_delta_th == pytest.approx(3.0)
    net.on_view_template(1, -rad, template_count=3, created=False)
    assert net.vt_delta_th == pytest.approx(-3.0)
    # delta_to corrects the decoded heading by the offset before the wrapped distance
    net.best = np.array([6.0, 6.0, 2.0])
    assert float(net.delta_to(np.array([6.0, 6.0, 5.0]))) == pytest.approx(0.0)


def test_attractor_step_on_a_packet_across_two_faces_equals_the_direct_convolution() -> None:
    """A compact packet on a large lattice: the attractor step equals the cell-by-cell spread."""
    p = departing().replace(pc_dim_xy=40, pc_dim_th=36)
    net = PoseCellNetwork(p)
    cells = np.zeros(net.shape)
    cells[np.ix_([39, 0, 1], [0, 1, 2], [35, 0, 1])] = np.random.default_rng(2).random((3, 3, 3))  # across 2 faces
    cells /= cells.sum()
    net.activity = cells.copy()
    net.step_attractor()

    excited = _direct_spread(cells, p.pc_w_e_dim, p.pc_w_e_var)
    expected = np.maximum(excited - _direct_spread(excited, p.pc_w_i_dim, p.pc_w_i_var) - p.pc_global_inhib, 0.0)
    expected /= expected.sum()
    assert np.allclose(net.activity, expected, rtol=0, atol=1e-15)
    assert np.count_nonzero(net.activity) == np.count_nonzero(expected)


def test_a_template_seen_for_hundreds_of_frames_saturates_without_overflow() -> None:
    net = _net(pc_dim_xy=11, pc_dim_th=12, vt_min_inject_age=0)
    net.on_view_template(0, 0.0, 1, created=True)
    before = net.activity.copy()
    net.on_view_template(0, 0.0, 1, created=False)  # decay 1 + 1 = 2: e^2.4 < 30, energy is injected
    assert net.activity.sum() > before.sum()
    for _ in range(800):  # decay grows by 1 − 0.05 a frame: 1.2·decay passes exp's range (~709) near 590
        net.on_view_template(0, 0.0, 1, created=False)
    saturated = net.activity.copy()
    net.on_view_template(0, 0.0, 1, created=False)
    np.testing.assert_array_equal(net.activity, saturated)  # nothing more is injected


@settings(max_examples=200, deadline=None, suppress_health_check=ONE_PATH)
@given(
    four_dof=st.booleans(),
    seed=st.integers(0, 10_000),
    offset=st.floats(-40.0, 40.0),
)
def test_distance_to_one_cell_equals_the_batched_distance_to_the_last_bit(
    four_dof: bool, seed: int, offset: float
) -> None:
    """``delta_to`` of one cell (every frame's question) is the row of the batched answer, bit for bit."""
    net = _net(pc_dim_xy=15, pc_dim_z=15, pc_dim_th=8) if four_dof else _net(pc_dim_xy=21, pc_dim_th=36)
    rng = np.random.default_rng(seed)
    net.best = rng.uniform(0.0, 1.0, net.rank) * net.dims
    net.vt_delta_th = offset
    cells = rng.uniform(-1.0, 2.0, (5, net.rank)) * net.dims
    cells[0] = net.best  # the packet's own cell (0 but for the heading offset)
    batched = net.delta_to(cells)
    for row, expected in zip(cells, batched, strict=True):
        assert net.delta_to(row) == expected

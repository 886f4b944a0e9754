"""The compiled pose-cell kernels against the numpy reference (bit for bit) and against independent arithmetic.

The compiled path (core/_posecell_kernel.py) visits only the slices that hold activity; the reference path
(core/posecells.py) computes the whole lattice. Both add the same products in the same order, so every cell,
the pre-scale total and the decoded centre must be equal to the last bit, on random packets and random dense
lattices, on the 3-DoF and the 4-DoF lattice, with and without ``openratslam_compat``. The independent checks
use dense circulant and shift matrices (the matrix form of Menezes et al. Eq. 3 and of the bilinear move),
which agree to rounding.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import core.posecells as posecells
from core import _posecell_kernel as kernels
from core.config import Departure, Params
from core.lattice import circulant_kernel
from core.posecells import PoseCellNetwork
from tests.core.conftest import departing

LATTICES = {
    "3dof": {"pc_dim_xy": 21, "pc_dim_th": 36, "pc_cell_x_size": 0.25},
    "small": {"pc_dim_xy": 11, "pc_dim_th": 12},
    "4dof": {"pc_dim_xy": 15, "pc_dim_z": 15, "pc_dim_th": 8, "pc_cell_x_size": 0.1, "pc_cell_z_size": 0.1},
    "compat": {"pc_dim_xy": 21, "pc_dim_th": 36, "openratslam_compat": True},
    "wide": {"pc_dim_xy": 48, "pc_dim_th": 24, "pc_w_e_dim": 9, "pc_w_i_dim": 7},
}


@pytest.fixture(autouse=True)
def loaded(monkeypatch: pytest.MonkeyPatch) -> None:
    """Load the kernels once; every test chooses its path (the flag is restored afterwards)."""
    kernels.load_compiled()
    monkeypatch.setattr(kernels, "_use_compiled", False)


def _activity(net: PoseCellNetwork, rng: np.random.Generator, dense: bool) -> np.ndarray:
    """A random dense lattice (``dense``), or a random packet of 1–5 cells a side, often across faces."""
    if dense:
        return rng.random(net.shape) ** 8
    size = int(rng.integers(1, 6))
    cells = np.zeros(net.shape)
    corner = [int(rng.integers(0, d)) for d in net.shape]
    cells[np.ix_(*[(c + np.arange(size)) % d for c, d in zip(corner, net.shape, strict=True)])] = rng.random(
        (size,) * net.rank
    )
    return cells / cells.sum()


def _on_path(compiled: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(kernels, "_use_compiled", compiled)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    lattice=st.sampled_from(sorted(LATTICES)),
    seed=st.integers(0, 100_000),
    dense=st.booleans(),
    moves=st.lists(
        st.tuples(st.floats(-3.0, 3.0), st.floats(-1.0, 1.0), st.floats(-0.3, 0.3), st.booleans()), min_size=1,
        max_size=5,
    ),
)
def test_the_compiled_update_equals_the_reference_to_the_last_bit(
    lattice: str, seed: int, dense: bool, moves: list[tuple[float, float, float, bool]],
    monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    params = departing().replace(**LATTICES[lattice])
    reference, compiled = PoseCellNetwork(params), PoseCellNetwork(params)
    start = _activity(reference, np.random.default_rng(seed), dense)
    reference.activity, compiled.activity = start.copy(), start.copy()
    for forward, dyaw, dz, still in moves:
        forward = 0.0 if still else forward  # a frame that only turns (or does not move)
        _on_path(False, monkeypatch)
        expected = reference.on_odo(forward, dyaw, dz)
        _on_path(True, monkeypatch)
        got = compiled.on_odo(forward, dyaw, dz)
        assert np.array_equal(compiled.activity, reference.activity)
        assert np.array_equal(got, expected)


@pytest.mark.parametrize("lattice", sorted(LATTICES))
def test_each_step_alone_equals_the_reference_to_the_last_bit(lattice: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """step_attractor, path_integrate and decode called one by one (each compiled one scans its input)."""
    params = departing().replace(**LATTICES[lattice])
    rng = np.random.default_rng(7)
    for _ in range(10):
        reference, compiled = PoseCellNetwork(params), PoseCellNetwork(params)
        start = _activity(reference, rng, dense=False)
        forward, dyaw, dz = (float(v) for v in rng.uniform(-2.0, 2.0, 3))
        for net, flag in ((reference, False), (compiled, True)):
            _on_path(flag, monkeypatch)
            net.activity = start.copy()
            net.step_attractor()
            net.path_integrate(forward, dyaw, dz)
        assert np.array_equal(compiled.activity, reference.activity)
        _on_path(False, monkeypatch)
        expected = reference.decode()
        _on_path(True, monkeypatch)
        assert np.array_equal(compiled.decode(), expected)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(lattice=st.sampled_from(sorted(LATTICES)), seed=st.integers(0, 100_000), dense=st.booleans())
def test_the_compiled_openratslam_decoding_equals_the_reference_to_the_last_bit(
    lattice: str, seed: int, dense: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The default engine decodes as OpenRatSLAM's code (part ``decode``): compiled and Python, the same bits."""
    params = Params().replace(**LATTICES[lattice])
    assert params.follows_openratslam(Departure.DECODE)
    net = PoseCellNetwork(params)
    net.activity = _activity(net, np.random.default_rng(seed), dense)
    _on_path(False, monkeypatch)
    expected = net.decode().copy()
    _on_path(True, monkeypatch)
    assert net.decode().tobytes() == expected.tobytes()


def _circulant_spread(cells: np.ndarray, size: int, var: float) -> np.ndarray:
    """Apply the (d, d) circulant matrix of the 1-D Gaussian along every axis (dense matrix products)."""
    for axis, dim in enumerate(cells.shape):
        matrix = circulant_kernel(dim, size, var)
        cells = np.moveaxis(np.tensordot(matrix, cells, axes=([1], [axis])), 0, axis)
    return cells


@pytest.mark.parametrize("lattice", ["3dof", "4dof", "wide"])
def test_the_compiled_attractor_equals_dense_circulant_products(lattice: str, monkeypatch: pytest.MonkeyPatch) -> None:
    params = departing().replace(**LATTICES[lattice])
    net = PoseCellNetwork(params)
    rng = np.random.default_rng(3)
    for dense in (False, True):
        cells = _activity(net, rng, dense)
        net.activity = cells.copy()
        _on_path(True, monkeypatch)
        net.step_attractor()
        excited = _circulant_spread(cells, params.pc_w_e_dim, params.pc_w_e_var)
        inhibited = _circulant_spread(excited, params.pc_w_i_dim, params.pc_w_i_var)
        expected = np.maximum(excited - inhibited - params.pc_global_inhib, 0.0)
        expected /= expected.sum()
        np.testing.assert_allclose(net.activity, expected, rtol=0, atol=1e-12)


def _shift_matrix(shift: float, dim: int) -> np.ndarray:
    """The (dim, dim) matrix that moves a wrapped axis by ``shift`` cells with linear weights (exact moves)."""
    whole = math.floor(shift)
    matrix = np.zeros((dim, dim))
    for i in range(dim):
        matrix[(i + whole) % dim, i] += 1.0 - (shift - whole)
        matrix[(i + whole + 1) % dim, i] += shift - whole
    return matrix


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 10_000), forward=st.floats(-4.0, 4.0), dyaw=st.floats(-1.5, 1.5))
def test_the_compiled_path_integration_equals_shift_matrices(
    seed: int, forward: float, dyaw: float, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Per heading layer k: X_k · P_k · Y_kᵀ (x then y), then the θ shift as one more matrix along θ."""
    params = departing().replace(pc_dim_xy=13, pc_dim_th=10, pc_cell_x_size=0.5)
    net = PoseCellNetwork(params)
    cells = np.random.default_rng(seed).random(net.shape)
    net.activity = cells.copy()
    _on_path(True, monkeypatch)
    net.path_integrate(forward, dyaw)
    v = forward / params.pc_cell_x_size
    moved = np.empty_like(cells)
    for k in range(net.shape[-1]):
        angle = k * 2.0 * math.pi / net.shape[-1]
        sx = 0.0 if abs(math.cos(angle)) < 1e-12 else v * math.cos(angle)
        sy = 0.0 if abs(math.sin(angle)) < 1e-12 else v * math.sin(angle)
        moved[:, :, k] = _shift_matrix(sx, 13) @ cells[:, :, k] @ _shift_matrix(sy, 13).T
    turned = np.tensordot(moved, _shift_matrix(dyaw / (2.0 * math.pi / 10), 10).T, axes=([2], [0]))
    np.testing.assert_allclose(net.activity, turned, rtol=0, atol=1e-12)


def test_the_first_maximum_wins_a_tie_on_both_paths(monkeypatch: pytest.MonkeyPatch) -> None:
    """Equal maxima: θ outermost, then y, x innermost; OpenRatSLAM's order (θ, x, y) with compat."""
    for compat, want in ((False, [8.0, 2.0, 3.0]), (True, [1.0, 5.0, 3.0])):
        params = departing().replace(pc_dim_xy=21, pc_dim_th=36, openratslam_compat=compat)
        for flag in (False, True):
            _on_path(flag, monkeypatch)
            net = PoseCellNetwork(params)
            net.activity[...] = 0.0
            net.activity[8, 2, 3] = net.activity[1, 5, 3] = net.activity[0, 0, 20] = 0.5
            assert net.decode() == pytest.approx(want, abs=1e-9)


def test_a_fully_inhibited_network_restarts_at_the_decoded_centre_on_both_paths(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    params = departing().replace(pc_dim_xy=11, pc_dim_th=12, pc_global_inhib=1.0)  # φ above every cell
    results = []
    for flag in (False, True):
        _on_path(flag, monkeypatch)
        net = PoseCellNetwork(params)
        net.best = np.array([3.7, 8.2, 5.9])
        net.step_attractor()
        results.append(net.activity.copy())
        assert net.activity[3, 8, 5] == 1.0 and net.activity.sum() == 1.0
        assert net.on_odo(0.0, 0.0) == pytest.approx([3.0, 8.0, 5.0])  # restarted again, decoded at the cell
    assert np.array_equal(results[0], results[1])


def test_a_network_switches_to_the_kernels_mid_run_without_changing_a_bit(monkeypatch: pytest.MonkeyPatch) -> None:
    """Loading the kernels after COMPILED_AFTER cell updates: the run equals one on the reference path throughout."""
    params = departing().replace(**LATTICES["3dof"])
    rng = np.random.default_rng(11)
    frames = [(float(rng.uniform(0.0, 0.4)), float(rng.uniform(-0.2, 0.2))) for _ in range(40)]
    links = [(int(rng.integers(0, 6)), float(rng.uniform(-0.3, 0.3))) for _ in range(40)]
    runs = []
    for after in (10**12, 15 * math.prod(params.lattice_shape)):  # never, and at the 15th update
        monkeypatch.setattr(posecells, "COMPILED_AFTER", after)
        monkeypatch.setattr(kernels, "_use_compiled", False)
        net = PoseCellNetwork(params.replace(vt_min_inject_age=0))
        centres = []
        for (forward, dyaw), (template, rad) in zip(frames, links, strict=True):
            net.on_view_template(template, rad, 6, created=template >= len(net._links_of_template))
            centres.append(net.on_odo(forward, dyaw).copy())
        assert kernels.enabled() == (after < 10**12)
        runs.append((np.array(centres), net.activity.copy()))
    assert np.array_equal(runs[0][0], runs[1][0])
    assert np.array_equal(runs[0][1], runs[1][1])


def test_writes_into_the_activity_between_updates_are_seen(monkeypatch: pytest.MonkeyPatch) -> None:
    """The compiled path keeps the lattice in reused slots; cells written from outside (an injection, a test that
    clears the lattice in place, an activity replaced after an in-place write) count like any others."""
    params = departing().replace(**LATTICES["3dof"])
    rng = np.random.default_rng(5)
    nets = {flag: PoseCellNetwork(params) for flag in (False, True)}
    writes = [
        lambda net: net.inject(np.array([3.0, 17.0, 30.0]), 0.4),
        lambda net: (net.activity.fill(0.0), net.activity.__setitem__((19, 2, 5), 1.0)),
        lambda net: (net.activity.fill(0.5), setattr(net, "activity", _activity(net, np.random.default_rng(9), False))),
    ]
    for index, write in enumerate(writes * 3):
        for _ in range(1 + index % 2):  # the writes fall on every slot in turn
            forward, dyaw = (float(v) for v in rng.uniform(-1.0, 1.0, 2))
            centres = []
            for flag, net in nets.items():
                _on_path(flag, monkeypatch)
                centres.append(net.on_odo(forward, dyaw))
            assert np.array_equal(centres[0], centres[1])
            assert np.array_equal(nets[False].activity, nets[True].activity)
        for net in nets.values():
            write(net)


def test_two_jobs_loading_the_kernels_at_once_compile_them_once() -> None:
    """A server runs jobs in threads: loading the kernels from several at once must wrap each function once (a
    second wrapping of a compiled function is numba's TypeError). Run in a fresh interpreter, nothing loaded."""
    import subprocess
    import sys

    code = (
        "import threading\n"
        "from core import _posecell_kernel as k\n"
        "gate = threading.Barrier(4)\n"
        "errors = []\n"
        "def load():\n"
        "    gate.wait()\n"
        "    try:\n"
        "        k.load_compiled()\n"
        "    except Exception as err:\n"
        "        errors.append(repr(err))\n"
        "threads = [threading.Thread(target=load) for _ in range(4)]\n"
        "[t.start() for t in threads]\n"
        "[t.join() for t in threads]\n"
        "assert not errors, errors\n"
        "assert k.enabled() and k.kernel('peak') is k.peak\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr[-2000:]

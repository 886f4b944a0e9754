"""``openratslam_compat``: each switched departure behaves as OpenRatSLAM's code, the default as before.

Every expected number is computed by hand from OpenRatSLAM's update rules (Ball et al. 2013; the
behaviour is described in core/compat.py and the module docstrings), and each compat test is paired with
the default behaviour it replaces.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from core import compat
from core.config import Departure, Params
from core.engine import Action, Engine
from core.experience_map import ExperienceMap
from core.motion import Motion
from core.posecells import PoseCellNetwork, _shift_weights
from tests.core.conftest import departing


@pytest.mark.parametrize(
    ("a", "b", "expected"),
    [
        (0.1, 0.3, 0.2),
        (0.3, 0.1, -0.2),
        (3.0, -3.0, 2 * math.pi - 6.0),  # across ±π: the short way is positive
        (-3.0, 3.0, -(2 * math.pi - 6.0)),
        # a half turn: direction clip_rad_180(π) = π > 0 and |0 − π| = π is not < 2π − π, so +(2π − π)
        (0.0, math.pi, math.pi),
    ],
)
def test_signed_delta_rad_takes_the_short_way(a: float, b: float, expected: float) -> None:
    assert compat.signed_delta_rad(a, b) == pytest.approx(expected, abs=1e-12)


def test_clip_rad_180_keeps_plus_pi_and_maps_minus_pi_to_it() -> None:
    assert compat.clip_rad_180(math.pi) == math.pi
    assert compat.clip_rad_180(-math.pi) == math.pi
    assert compat.clip_rad_180(3 * math.pi / 2) == pytest.approx(-math.pi / 2)


@given(st.floats(-20.0, 20.0), st.floats(-20.0, 20.0))
def test_signed_delta_rad_is_the_wrapped_difference(a: float, b: float) -> None:
    d = compat.signed_delta_rad(a, b)
    assert -math.pi - 1e-9 <= d <= math.pi + 1e-9
    assert math.cos(a + d) == pytest.approx(math.cos(b), abs=1e-9)
    assert math.sin(a + d) == pytest.approx(math.sin(b), abs=1e-9)


def test_iterate_moves_both_ends_by_half_the_miss() -> None:
    # link 0 → 1 says "1 m ahead"; 1 sits 2 m ahead and turned 0.2 rad: c = 0.5 splits both misses equally
    poses = np.array([[0.0, 0.0, 0.0, 0.0], [2.0, 0.0, 0.0, 0.2]])
    transform = np.array([[1.0, 0.0, 0.0, 0.0]])
    compat.iterate(poses, np.array([0]), np.array([1]), transform, loops=1, correction=0.5)
    np.testing.assert_allclose(poses[:, [0, 1, 3]], [[0.5, 0.0, 0.1], [1.5, 0.0, 0.1]], atol=1e-15)


def test_iterate_is_sequential_in_source_order() -> None:
    # Two links into experience 2 from 0 and 1 (created 1→2 first): OpenRatSLAM visits 0→2 before 1→2.
    # 0 at x=0, 1 at x=10, 2 at x=4; both links say "2 is 1 m ahead" (headings 0), c = 0.5.
    # 0→2: miss 4−1 = 3 → e0 = 1.5, e2 = 2.5. Then 1→2: predicted 11, miss 2.5−11 = −8.5 → e1 = 5.75, e2 = 6.75.
    poses = np.array([[0.0, 0, 0, 0], [10.0, 0, 0, 0], [4.0, 0, 0, 0]])
    transform = np.array([[1.0, 0, 0, 0], [1.0, 0, 0, 0]])
    compat.iterate(poses, np.array([1, 0]), np.array([2, 2]), transform, loops=1, correction=0.5)
    np.testing.assert_allclose(poses[:, 0], [1.5, 5.75, 6.75], atol=1e-12)


def _weights_on(shift: float, dim: int, one_cell: bool) -> np.ndarray:
    """Where one cell at 0 goes on a ``dim``-cell axis moved by ``shift`` cells: its weight at every cell."""
    whole, frac = _shift_weights(np.array([shift]), one_cell)
    out = np.zeros(dim)
    out[int(whole[0]) % dim] += 1.0 - frac[0]
    out[(int(whole[0]) + 1) % dim] += frac[0]
    return out


def test_one_cell_translation_extrapolates_like_openratslam() -> None:
    # 1.5 cells: OpenRatSLAM keeps 1 − 1.5 = −0.5 in place and moves 1.5 one cell; exact: half to +1, half to +2
    np.testing.assert_allclose(_weights_on(1.5, 5, one_cell=True), [-0.5, 1.5, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(_weights_on(1.5, 5, one_cell=False), [0.0, 0.5, 0.5, 0.0, 0.0])
    # under one cell (either sign) both are the same four-neighbour weights
    for s in (0.25, -0.25, 1.0, -1.0):
        np.testing.assert_allclose(_weights_on(s, 5, one_cell=True), _weights_on(s, 5, one_cell=False), atol=1e-15)


def _young_map(compat_flag: bool) -> PoseCellNetwork:
    net = PoseCellNetwork(departing(openratslam_compat=compat_flag, pc_dim_xy=11, pc_dim_th=12))
    for template in range(3):  # three new templates, all linked to the centre (5, 5, 6)
        net.on_view_template(template, 0.0, template + 1, created=True)
    return net


def test_young_map_injection_follows_the_unsigned_wrap_in_compat() -> None:
    net = _young_map(True)
    before = net.activity[5, 5, 6]
    net.on_view_template(0, 0.0, 3, created=False)  # 3 templates < 10: OpenRatSLAM's size() − 10 wraps
    energy = 0.15 / 30.0 * (30.0 - math.exp(1.2 * 1.0))
    assert net.activity[5, 5, 6] == pytest.approx(before + energy)


def test_young_map_does_not_inject_by_default() -> None:
    net = _young_map(False)
    before = net.activity.copy()
    net.on_view_template(0, 0.0, 3, created=False)
    np.testing.assert_array_equal(net.activity, before)


def _two_experiences(compat_flag: bool) -> ExperienceMap:
    em = ExperienceMap(departing(openratslam_compat=compat_flag, exp_initial_em_deg=0.0), 3)
    em.on_odo(Motion(1.0, 0.0, 0.0, 0.0, 2.0))
    em.create_experience(0, np.zeros(3), 2.0, 0)
    em.on_odo(Motion(1.0, 0.5, 0.3, math.pi / 2, 3.0))
    em.create_experience(1, np.zeros(3), 5.0, 0)
    return em


def test_compat_odometry_turns_first_and_ignores_sideways_motion() -> None:
    em = _two_experiences(True)
    # turn to π/2, then 1 m along it; the 0.5 m sideways and 0.3 m up are ignored; Δt counts from the start
    np.testing.assert_allclose(em.poses[1], [1.0, 1.0, 0.0, math.pi / 2], atol=1e-12)
    assert em.links[3][0] == pytest.approx(5.0)


def test_default_odometry_moves_before_turning_and_restarts_dt() -> None:
    em = _two_experiences(False)
    np.testing.assert_allclose(em.poses[1], [2.0, 0.5, 0.3, math.pi / 2], atol=1e-12)
    assert em.links[3][0] == pytest.approx(3.0)


def _engine_run(compat_flag: bool) -> tuple[Engine, list[Action], list[np.ndarray]]:
    params = departing(openratslam_compat=compat_flag, template_x_size=4, template_y_size=2, vt_shift_match=1,
                    vt_step_match=1, exp_loops=3, vt_min_inject_age=0)  # young templates inject in both
    engine = Engine(params)
    rng = np.random.default_rng(3)
    views = [rng.integers(0, 255, (8, 8), dtype=np.uint8) for _ in range(4)]
    actions, poses = [], []
    for frame in range(12):
        result = engine.step(views[frame % 4], Motion(0.3, 0.0, 0.0, 0.4, 1.0), float(frame))
        actions.append(result.action)
        poses.append(engine.map.poses.copy())
    return engine, actions, poses


def test_compat_relaxes_only_on_action_frames_and_never_settles() -> None:
    engine, actions, poses = _engine_run(True)
    assert Action.CREATE_EDGE in actions  # the four views repeat: loop closures happen
    for frame in range(1, len(actions)):
        if actions[frame] == Action.NONE:  # no action, no relaxation: the map stands still
            np.testing.assert_array_equal(poses[frame], poses[frame - 1])
    before = engine.map.poses.copy()
    assert engine.settle() == 0
    np.testing.assert_array_equal(engine.map.poses, before)
    # nothing is anchored: the first experience was pulled away from where it was created
    assert np.abs(engine.map.poses[0] - poses[0][0]).max() > 1e-3


def test_default_keeps_the_first_experience_anchored() -> None:
    engine, actions, poses = _engine_run(False)
    assert Action.CREATE_EDGE in actions
    engine.settle()
    np.testing.assert_array_equal(engine.map.poses[0], poses[0][0])


def test_flat_patch_normalises_to_one_in_compat_and_half_by_default() -> None:
    from core.localview import patch_normalise

    flat = np.full((3, 4), 0.25)  # every patch has σ = 0: OpenRatSLAM's 0/0 is clamped to 1.0
    np.testing.assert_array_equal(patch_normalise(flat, 1, 0.0, 1.0), np.ones((3, 4)))
    np.testing.assert_array_equal(patch_normalise(flat, 1, 0.0), np.full((3, 4), 0.5))


def test_visual_odometry_rate_is_camera_hz_in_compat_and_one_over_dt_by_default() -> None:
    from core.visual_odometry import VisualOdometry

    rng = np.random.default_rng(5)
    first = rng.integers(0, 255, (6, 100), dtype=np.uint8)
    second = np.roll(first, 3, axis=1)
    rates = []
    for flag in (False, True):
        vo = VisualOdometry(departing(openratslam_compat=flag, camera_hz=10.0, camera_fov_deg=50.0))
        vo.process(first, 0.0)
        rates.append(vo.process(second, 0.5)[1])
    assert abs(rates[0]) == pytest.approx(3 * math.radians(50.0) / 100 * 2.0)  # 1/dt = 2 Hz
    assert rates[1] == pytest.approx(5.0 * rates[0])  # camera_hz = 10 Hz


def _one_cell(compat_flag: bool, x: int, y: int) -> PoseCellNetwork:
    net = PoseCellNetwork(departing(openratslam_compat=compat_flag, pc_dim_xy=5, pc_dim_th=4))
    net.activity[...] = 0.0
    net.activity[x, y, 0] = 1.0
    net.path_integrate(forward_m=0.5, dyaw_rad=0.0)  # layer 0 (heading 0) moves half a cell along +x
    return net


def test_compat_loses_what_wraps_into_the_corner_from_the_edge_like_openratslam() -> None:
    # OpenRatSLAM's wrap-back loops start at 1: from (4, 0) the half that crosses the +x face towards the
    # corner (0, 0) is lost (layer 0 is not rotated, so (0, 0) is its rotated corner)
    net = _one_cell(True, 4, 0)
    assert net.activity[4, 0, 0] == pytest.approx(0.5)
    assert net.activity[0, 0, 0] == pytest.approx(0.0, abs=1e-15)


def test_default_and_compat_wrap_the_edge_elsewhere() -> None:
    exact = _one_cell(False, 4, 0)
    assert exact.activity[0, 0, 0] == pytest.approx(0.5)  # the default keeps it
    away = _one_cell(True, 4, 2)  # away from the corner compat wraps as well
    assert away.activity[0, 2, 0] == pytest.approx(0.5)
    assert away.activity.sum() == pytest.approx(1.0)


def _map_with(parts: str) -> ExperienceMap:
    em = ExperienceMap(Params(openratslam_parts=parts, exp_initial_em_deg=0.0), 3)
    em.on_odo(Motion(1.0, 0.0, 0.0, 0.0, 2.0))
    em.create_experience(0, np.zeros(3), 2.0, 0)
    em.on_odo(Motion(1.0, 0.5, 0.3, math.pi / 2, 3.0))
    em.create_experience(1, np.zeros(3), 5.0, 0)
    return em


def test_openratslam_parts_switch_one_departure_each() -> None:
    # the same two experiences as _two_experiences: odometry alone turns first (compat's pose) but keeps the
    # default Δt; link_dt alone counts Δt from the start (compat's) but composes the motion exactly (default's)
    odometry, link_dt = _map_with("odometry"), _map_with("link_dt")
    np.testing.assert_allclose(odometry.poses[1], [1.0, 1.0, 0.0, math.pi / 2], atol=1e-12)
    assert odometry.links[3][0] == pytest.approx(3.0)
    np.testing.assert_allclose(link_dt.poses[1], [2.0, 0.5, 0.3, math.pi / 2], atol=1e-12)
    assert link_dt.links[3][0] == pytest.approx(5.0)
    # injection alone: a young map injects as OpenRatSLAM's unsigned wrap lets it
    net = PoseCellNetwork(Params(openratslam_parts="injection", pc_dim_xy=11, pc_dim_th=12))
    for template in range(3):
        net.on_view_template(template, 0.0, template + 1, created=True)
    before = net.activity[5, 5, 6]
    net.on_view_template(0, 0.0, 3, created=False)
    assert net.activity[5, 5, 6] == pytest.approx(before + 0.15 / 30.0 * (30.0 - math.exp(1.2)))


def test_every_part_named_is_compat_and_the_default_makes_openratslams_decisions() -> None:
    """``all`` runs as compat bit for bit; ``none`` as every departure; the default (pose cells as OpenRatSLAM's)
    takes OpenRatSLAM's decisions — the same template, action and experience on every frame — and differs only
    in the map it relaxes from them, where ``none``'s decisions part from compat's."""

    def run(params: Params) -> tuple[dict[str, np.ndarray], np.ndarray]:
        engine = Engine(params)
        rng = np.random.default_rng(3)
        views = [rng.integers(0, 255, (8, 8), dtype=np.uint8) for _ in range(6)]
        trace = []
        for frame in range(40):  # 1.3 cells a frame: OpenRatSLAM's one-cell weights and the exact ones differ
            result = engine.step(views[frame % 6], Motion(1.3, 0.0, 0.0, 0.3, 1.0), float(frame))
            trace.append((result.template, int(result.action), result.experience))
        engine.settle()
        return engine.snapshot(), np.array(trace)

    base = Params(template_x_size=4, template_y_size=2, vt_shift_match=1, vt_step_match=1, exp_loops=3)
    everything, compat_run = run(base.replace(openratslam_parts="all")), run(base.replace(openratslam_compat=True))
    for key in compat_run[0]:
        np.testing.assert_array_equal(everything[0][key], compat_run[0][key], err_msg=key)
    default, departed = run(base), run(base.replace(openratslam_parts="none"))
    np.testing.assert_array_equal(default[1], compat_run[1])  # must: the same decisions, frame for frame
    assert not np.array_equal(departed[1], compat_run[1])  # the exact translation decides otherwise
    assert not np.array_equal(default[0]["em_pose"], compat_run[0]["em_pose"])  # the map is relaxed our way


def test_an_unknown_part_is_a_config_error_naming_the_valid_ones() -> None:
    from core.config import ConfigError

    with pytest.raises(ConfigError, match=r"unknown part 'relax' \(valid: all, none, odometry, link_dt, relaxation"):
        Params(openratslam_parts="relaxation,relax")
    assert Params(openratslam_parts=" Relaxation , decode ").follows_openratslam(Departure.DECODE)

"""The engine end to end on a strip world: loop closure, determinism, snapshot/restore, 4-DoF z."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

from core import Engine
from core.config import Params
from core.engine import Action
from core.motion import Motion
from tests.worlds import StripWorld, smooth_panorama


def _params(**changes: object) -> Params:
    base: dict[str, object] = {
        "template_x_size": 32, "template_y_size": 12, "vt_shift_match": 2, "vt_step_match": 1,
        "vt_match_threshold": 0.03, "pc_dim_xy": 21, "pc_dim_th": 36, "pc_cell_x_size": 1.0,
        "exp_delta_pc_threshold": 2.0, "exp_loops": 20, "vt_min_inject_age": 5, "exp_initial_em_deg": 0.0,
    }
    base.update(changes)
    return Params().replace(**base)


def _run(engine: Engine, frames: list[tuple[np.ndarray, Motion, float]]) -> list:
    return [engine.step(img, motion, stamp) for img, motion, stamp in frames]


def _assert_same_state(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert a[key].dtype == b[key].dtype, key
        assert np.array_equal(a[key], b[key], equal_nan=True), key


def test_second_lap_closes_the_loop(strip_world: StripWorld) -> None:
    frames = list(strip_world.drive(laps=2.0, yaw_bias=0.01))
    engine = Engine(_params())
    results = _run(engine, frames)
    lap = len(frames) // 2
    second = results[lap + 2 :]
    matched = sum(not r.template_created for r in second)
    assert matched / len(second) >= 0.95
    assert engine.loop_closures >= 1
    assert any(r.action == Action.CREATE_EDGE for r in second)
    assert engine.experience_count < 1.3 * len({r.experience for r in results[:lap]})


def test_same_frames_give_the_same_map_bit_for_bit(strip_world: StripWorld) -> None:
    frames = list(strip_world.drive(laps=1.5))
    a, b = Engine(_params()), Engine(_params())
    _run(a, frames)
    _run(b, frames)
    _assert_same_state(a.snapshot(), b.snapshot())


@pytest.mark.parametrize("k", [1, 37, 100])
def test_snapshot_restore_continues_bit_for_bit(strip_world: StripWorld, k: int) -> None:
    frames = list(strip_world.drive(laps=1.6, yaw_bias=0.02))
    whole = Engine(_params(), origin=1)
    _run(whole, frames)
    first = Engine(_params(), origin=1)
    _run(first, frames[:k])
    buffer = io.BytesIO()
    np.savez(buffer, **first.snapshot())  # plain arrays survive a file round trip
    buffer.seek(0)
    with np.load(buffer) as data:
        state = {key: data[key] for key in data.files}
    resumed = Engine.restore(_params(), state, origin=1)
    _run(resumed, frames[k:])
    _assert_same_state(whole.snapshot(), resumed.snapshot())


def test_visual_odometry_is_used_without_odometry(strip_world: StripWorld) -> None:
    engine = Engine(_params())
    for img, _, stamp in list(strip_world.drive(laps=0.2)):
        result = engine.step(img, None, stamp)
    assert result.motion.dt == pytest.approx(0.5)
    assert engine.experience_count >= 1


def test_4dof_lattice_integrates_z() -> None:
    params = _params(pc_dim_xy=15, pc_dim_z=15, pc_dim_th=8, pc_cell_x_size=0.1, pc_cell_z_size=0.1,
                     exp_delta_pc_threshold=2.0)
    engine = Engine(params)
    world = StripWorld(perimeter_m=400.0, seed=9)
    z = 0.0
    centre_z = 7.0
    for i in range(12):
        motion = Motion(0.0, 0.0, 0.0, 0.0, 0.0) if i == 0 else Motion(0.02, 0.0, 0.05, 0.0, 0.5)
        z += motion.dz
        engine.step(world.view(30.0 * i), motion, 0.5 * i)  # distinct places
        # the packet moves dz / pc_cell_z_size = 0.5 z-cells per frame, wrapping at 15 (the ±3-cell
        # decoding window is asymmetric about a half-cell packet: up to ~0.05 cell bias)
        assert engine.pose_cells.best[2] == pytest.approx((centre_z + z / 0.1) % 15, abs=0.1)
    poses = engine.map.poses
    stamps = engine.map.snapshot()["em_stamp"]
    assert poses[:, 2] == pytest.approx(0.05 * np.maximum(stamps / 0.5, 0))
    assert poses[-1, 2] > 0.3


def test_experiences_follow_the_threshold(strip_world: StripWorld) -> None:
    engine = Engine(_params(exp_delta_pc_threshold=2.0))
    results = _run(engine, list(strip_world.drive(laps=0.9)))
    created = [r.frame for r in results if r.action == Action.CREATE_NODE]
    new_templates = [r.frame for r in results if r.template_created]
    # first lap: a template with no experience yet always creates one (get_action's first rule); the view
    # moves 4 px per frame and the matcher absorbs ±4 px, so templates (and experiences) come every 2nd frame
    assert set(new_templates) <= set(created)
    assert np.diff(created).max() <= 3
    poses = engine.map.poses
    steps = np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1)
    assert steps.max() <= 3 * 0.5 + 1e-9


def test_shortest_path_through_the_engine(strip_world: StripWorld) -> None:
    engine = Engine(_params())
    _run(engine, list(strip_world.drive(laps=0.5)))
    n = engine.experience_count
    result = engine.shortest_path(0, n - 1, "distance")
    assert result.nodes[0] == 0 and result.nodes[-1] == n - 1
    assert result.cost == pytest.approx(float(np.sum(engine.map.links[4][: n - 1])), rel=1e-9)
    assert math.isfinite(engine.shortest_path(0, n - 1, "time").cost)


def _engine_with_experiences(coords: list[list[float]], templates: list[int]) -> Engine:
    """An engine whose map holds experiences at lattice ``coords`` (x, y, th) created with ``templates``."""
    engine = Engine(_params(exp_delta_pc_threshold=2.0))
    for coord, template in zip(coords, templates, strict=True):
        engine.map.create_experience(template, np.asarray(coord, dtype=float), 0.0, 0)
    return engine


def _action(engine: Engine, template: int, best: list[float], prev_vt: int) -> tuple[Action, int]:
    engine.pose_cells.best = np.asarray(best, dtype=float)
    engine.pose_cells.prev_vt = prev_vt
    return engine._get_action(template)


def test_get_action_follows_openratslam() -> None:
    """OpenRatSLAM PosecellNetwork::get_action, case by case (threshold 2 cells, wrapped distances)."""
    # experiences 0 (template 0) and 1 (template 1, current)
    engine = _engine_with_experiences([[5.0, 5.0, 5.0], [10.0, 10.0, 10.0]], [0, 1])
    assert engine.map.current == 1
    # a template without experiences: create one
    assert _action(engine, 2, [10.0, 10.0, 10.0], prev_vt=1) == (Action.CREATE_NODE, -1)
    # same template, packet within the threshold of the current experience: nothing
    assert _action(engine, 1, [11.0, 11.0, 10.0], prev_vt=1) == (Action.NONE, -1)
    # same template, packet moved away, no other experience of it: a new experience
    assert _action(engine, 1, [13.0, 10.0, 10.0], prev_vt=1) == (Action.CREATE_NODE, -1)
    # template changed to one whose experience is close (across the x face: 20 → 0 is 1 cell): a link
    engine_wrap = _engine_with_experiences([[0.5, 5.0, 5.0], [10.0, 10.0, 10.0]], [0, 1])
    assert _action(engine_wrap, 0, [20.0, 5.0, 5.0], prev_vt=1) == (Action.CREATE_EDGE, 0)
    # template changed, its experience too far (3 cells): a new experience
    assert _action(engine, 0, [8.0, 5.0, 5.0], prev_vt=1) == (Action.CREATE_NODE, -1)
    # the current experience is never the link target, even if it is the closest
    engine_two = _engine_with_experiences([[5.0, 5.0, 5.0], [6.0, 5.0, 5.0]], [0, 0])
    assert engine_two.map.current == 1
    assert _action(engine_two, 0, [6.0, 5.0, 5.0], prev_vt=1) == (Action.CREATE_EDGE, 0)


@pytest.mark.parametrize(
    ("lever", "slack", "expected"),
    [
        (0.0, 0.2, (Action.CREATE_NODE, -1)),  # made by the map itself: OpenRatSLAM's gate, 3 cells > 2
        (12.0, 0.0, (Action.CREATE_NODE, -1)),  # moved by a merge, no slack: the same gate
        (4.0, 0.2, (Action.CREATE_NODE, -1)),  # gate 2 + 0.2·4 = 2.8 < 3
        (6.0, 0.2, (Action.CREATE_EDGE, 0)),  # gate 2 + 0.2·6 = 3.2 > 3: the loop closes
    ],
)
def test_an_experience_a_merge_moved_gets_a_closure_gate_wider_by_its_lever(
    lever: float, slack: float, expected: tuple[Action, int]
) -> None:
    """``exp_delta_pc_threshold + merge_lattice_slack · em_pc_lever``: experience 0 lies 3 cells from the packet."""
    engine = _engine_with_experiences([[5.0, 5.0, 5.0], [10.0, 10.0, 10.0]], [0, 1])
    state = engine.snapshot()
    state["em_pc_lever"] = np.array([lever, 0.0])
    restored = Engine.restore(_params(exp_delta_pc_threshold=2.0, merge_lattice_slack=slack), state)
    assert restored.map.lattice_levers.tolist() == [lever, 0.0]
    assert restored.snapshot()["em_pc_lever"].tolist() == [lever, 0.0]
    assert _action(restored, 0, [8.0, 5.0, 5.0], prev_vt=1) == expected


def test_of_the_experiences_within_their_gates_the_closest_is_linked() -> None:
    """Template 0 has experience 0 (made by the map, 1.5 cells from the packet) and experience 1 (moved by a merge,
    lever 20: gate 2 + 4 = 6, 1.8 cells away): OpenRatSLAM links the closest, 0, and so does the widened gate
    (a wider gate must not trade a closure the plain gate makes for one onto the moved experience)."""
    engine = _engine_with_experiences([[6.5, 5.0, 5.0], [9.8, 5.0, 5.0], [12.0, 12.0, 12.0]], [0, 0, 1])
    state = engine.snapshot()
    state["em_pc_lever"] = np.array([0.0, 20.0, 0.0])
    restored = Engine.restore(_params(exp_delta_pc_threshold=2.0, merge_lattice_slack=0.2), state)
    assert _action(restored, 0, [8.0, 5.0, 5.0], prev_vt=1) == (Action.CREATE_EDGE, 0)
    assert _action(restored, 0, [11.0, 5.0, 5.0], prev_vt=1) == (Action.CREATE_EDGE, 1)  # 0 is 4.5 cells off


def test_poseidon_state_restores_bit_for_bit() -> None:
    """4-DoF lattice, VPR Guard, motion gate and clamps: processing 1..N equals 1..k, snapshot, restore, k+1..N."""
    params = _params(pc_dim_xy=9, pc_dim_z=5, pc_dim_th=8, pc_cell_x_size=0.5, pc_cell_z_size=0.5,
                     vpr_guard=True, vpr_window=6, vpr_min_rep=2, vpr_leak_rate=4, motion_gate=True,
                     max_correction_step=0.05, max_correction_norm=1.0, exp_relax_batch=3)
    world = StripWorld(perimeter_m=30.0, seed=5)
    frames = []
    for i, (image, motion, stamp) in enumerate(world.drive(laps=2.2, yaw_bias=0.03)):
        frames.append((image, Motion(motion.dx, motion.dy, 0.02 * math.sin(i / 5), motion.dyaw, motion.dt), stamp))
    whole = Engine(params)
    _run(whole, frames)
    assert whole.experience_count > 3
    first = Engine(params)
    _run(first, frames[:70])
    resumed = Engine.restore(params, first.snapshot())
    _run(resumed, frames[70:])
    _assert_same_state(whole.snapshot(), resumed.snapshot())


@pytest.mark.parametrize(
    ("second_origin", "changes", "joins"),
    [
        (1, {}, True),  # a closure from session 1's experience onto session 0's: the view's heading
        (0, {}, False),  # both experiences of one session: OpenRatSLAM's closure, no offset
        (0, {"exp_relax_joint": True}, True),  # a map settled on the joint least squares (as a merged map is)
        (1, {"merge_view_heading": False}, False),  # the key off: OpenRatSLAM's closure
        (1, {"openratslam_compat": True}, False),
    ],
)
def test_a_closure_that_joins_two_sessions_or_closes_a_merged_map_takes_the_views_heading(
    second_origin: int, changes: dict[str, object], joins: bool
) -> None:
    """``merge_view_heading``: view A makes experience 0 (origin 0); views B and C (A upside down, A inverted), a
    step on each, experiences 1 and 2 (origin ``second_origin``); A again, turned left by 5 of 256 pixels of a 360°
    camera, closes 2 → 0. With no turn in the odometry the link's heading change is the view's: −5·2π/256
    (experience 0 faces that far right of the robot), and the robot's facing restarts 5·2π/256 left of experience
    0's. So it is in a map settled on the joint least squares. Within one session's map (or with the key off) a
    forward view's closure has no offset: 0 and experience 0's facing."""
    params = _params(template_x_size=128, template_y_size=32, vt_shift_match=10, vt_step_match=2,
                     vt_match_threshold=0.02, camera_fov_deg=360.0, **changes)  # fmt: skip
    engine = Engine(params, origin=0)
    a = smooth_panorama()
    step = Motion(0.1, 0.0, 0.0, 0.0, 0.1)
    engine.step(a, step, 0.0)
    engine.origin = second_origin
    engine.step(np.flipud(a), step, 0.1)
    engine.step(255 - a, step, 0.2)
    result = engine.step(np.roll(a, 5, axis=1), step, 0.3)
    assert result.action == Action.CREATE_EDGE and engine.map.current == 0
    source, target, transform = (view[-1] for view in engine.map.links[:3])
    assert (source, target) == (2, 0)
    turn = 5 * 2 * math.pi / 256 if joins else 0.0
    assert transform[3] == pytest.approx(-turn, abs=0.1 * 2 * math.pi / 128)
    assert engine.map.accum[3] == pytest.approx(engine.map.poses[0, 3] + turn, abs=0.1 * 2 * math.pi / 128)

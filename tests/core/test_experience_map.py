"""Experience creation, links in the source frame, 3-D relaxation that closes a square loop."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.config import Params
from core.experience_map import ExperienceMap, LinkKind
from core.motion import Motion
from core.relaxation import PairSet


def _em(**changes: object) -> ExperienceMap:
    return ExperienceMap(Params().replace(**{"exp_initial_em_deg": 0.0, **changes}), 3)


def _residuals(em: ExperienceMap) -> np.ndarray:
    src, dst, t, _, _, _ = em.links
    p = em.poses
    yaw = p[src, 3]
    pred_x = p[src, 0] + np.cos(yaw) * t[:, 0] - np.sin(yaw) * t[:, 1]
    pred_y = p[src, 1] + np.sin(yaw) * t[:, 0] + np.cos(yaw) * t[:, 1]
    return np.stack([p[dst, 0] - pred_x, p[dst, 1] - pred_y, p[dst, 2] - (p[src, 2] + t[:, 2])], axis=1)


def test_new_experience_is_previous_plus_accumulated_odometry() -> None:
    em = _em()
    em.create_experience(0, np.zeros(3), 0.0, origin=7)
    em.on_odo(Motion(3.0, 0.0, 1.0, math.pi / 2, 2.0))
    em.on_odo(Motion(2.0, 0.0, 0.0, 0.0, 1.0))  # now facing +y
    e1 = em.create_experience(1, np.ones(3), 3.0, origin=7)
    assert em.poses[e1] == pytest.approx([3.0, 2.0, 1.0, math.pi / 2])
    src, dst, t, dt, dist, kind = em.links
    assert (int(src[0]), int(dst[0])) == (0, 1)
    assert t[0] == pytest.approx([3.0, 2.0, 1.0, math.pi / 2])  # source frame = map frame (yaw 0)
    assert dt[0] == pytest.approx(3.0)
    assert dist[0] == pytest.approx(math.sqrt(9 + 4 + 1))
    assert kind[0] == LinkKind.ODOMETRY
    assert em.current == 1 and em.previous == 0


def test_link_transform_is_in_the_source_frame() -> None:
    em = _em(exp_initial_em_deg=90.0)
    em.create_experience(0, np.zeros(3), 0.0, 0)  # facing +y
    em.on_odo(Motion(2.0, 0.0, 0.0, 0.0, 1.0))  # 2 m along +y in the map
    em.create_experience(1, np.zeros(3), 1.0, 0)
    assert em.poses[1][:2] == pytest.approx([0.0, 2.0])
    assert em.links[2][0] == pytest.approx([2.0, 0.0, 0.0, 0.0])  # 2 m ahead of the source


def test_duplicate_links_are_not_added_in_either_direction() -> None:
    """OpenRatSLAM ``on_create_link``: no second link between two experiences, whatever its direction."""
    em = _em()
    em.create_experience(0, np.zeros(3), 0.0, 0)
    em.on_odo(Motion(1.0, 0.0, 0.0, 0.0, 1.0))
    em.create_experience(1, np.zeros(3), 1.0, 0)  # odometry link 0 → 1
    em.on_odo(Motion(1.0, 0.0, 0.0, 0.0, 1.0))
    em.create_experience(2, np.zeros(3), 2.0, 0)  # odometry link 1 → 2
    assert em.create_link(1, 0, 0.0, LinkKind.LOOP) is False  # reverse of 0 → 1
    assert em.create_link(2, 0, 0.0, LinkKind.LOOP) is True
    assert em.create_link(2, 0, 0.0, LinkKind.LOOP) is False
    assert em.create_link(0, 2, 0.0, LinkKind.LOOP) is False
    assert em.link_count == 3


def test_a_restored_map_refuses_the_links_it_was_restored_with_and_those_added_since() -> None:
    """The restored links' pairs are one sorted array, those added later a set: a link is refused in either
    direction against both (create_link), in its own direction by add_link_raw; ids past 2¹⁶ keep their pairs
    apart, and the restored pairs take 8 bytes a link."""
    em = _em()
    for e in range(4):
        em.create_experience(e, np.zeros(3), float(e), 0)  # odometry links 0 → 1 → 2 → 3
        em.on_odo(Motion(1.0, 0.0, 0.0, 0.0, 1.0))
    back = ExperienceMap.restore(em.params, 3, em.snapshot())
    assert back._pairs._sorted.nbytes == 8 * 3
    assert back.create_link(2, 1, 0.0, LinkKind.LOOP) is False  # reverse of a restored link
    assert back.add_link_raw(1, 2, np.zeros(4), 0.0, 0.0, LinkKind.MERGE) is False
    assert back.add_link_raw(2, 1, np.zeros(4), 0.0, 0.0, LinkKind.MERGE) is True
    assert back.create_link(3, 0, 0.0, LinkKind.LOOP) is True
    assert back.create_link(0, 3, 0.0, LinkKind.LOOP) is False  # reverse of one added since the restore
    assert back.add_link_raw(3, 0, np.zeros(4), 0.0, 0.0, LinkKind.MERGE) is False
    assert back.link_count == 5
    far = PairSet(np.array([1, 2**16]), np.array([2**16, 1]))
    assert (1, 2**16) in far and (2**16, 1) in far and (1, 1) not in far and (2**16, 2**16) not in far


def test_relaxation_closes_a_square_loop_with_known_odometry_error() -> None:
    """Sides 10, 10, 10 then a closure claiming 12 m: LS spreads the 2 m misclosure, 0.5 m per link."""
    em = _em(exp_correction=0.5, exp_loops=5000, exp_relax_tolerance=1e-9)
    em.create_experience(0, np.zeros(3), 0.0, 0)
    for k in range(1, 4):
        em.on_odo(Motion(10.0, 0.0, 0.0, 0.0, 10.0))
        em.create_experience(k, np.zeros(3), 10.0 * k, 0)
        em.on_odo(Motion(0.0, 0.0, 0.0, math.pi / 2, 1.0))
    assert em.poses[3][:2] == pytest.approx([0.0, 10.0])
    em.on_odo(Motion(12.0, 0.0, 0.0, math.pi / 2, 12.0))  # 12 m instead of 10, then face e0's heading again
    assert em.create_link(3, 0, 0.0, LinkKind.LOOP)
    before = _residuals(em)
    assert before[-1] == pytest.approx([0.0, 2.0, 0.0])
    assert em.relax_pending
    em.relax()
    assert not em.relax_pending
    after = _residuals(em)
    assert np.allclose(after, np.tile([0.0, 0.5, 0.0], (4, 1)), atol=1e-6)
    yaws = em.poses[:, 3]
    assert yaws == pytest.approx([0.0, 0.0, math.pi / 2, math.pi])  # each created facing its arrival heading


def test_relaxation_fixed_point_matches_linear_least_squares() -> None:
    """Independent check: positions solve the normal equations of Σ‖p_j − p_i − R_i t_ij‖² for the final yaws."""
    rng = np.random.default_rng(4)
    em = _em(exp_loops=20000, exp_relax_tolerance=1e-11)
    em.create_experience(0, np.zeros(3), 0.0, 0)
    for k in range(1, 12):
        em.on_odo(Motion(2.0 + rng.normal(0, 0.2), 0.0, rng.normal(0, 0.1), 2 * math.pi / 12 + rng.normal(0, 0.05), 1))
        em.create_experience(k, np.zeros(3), float(k), 0)
    em.on_odo(Motion(2.0, 0.0, 0.0, 2 * math.pi / 12, 1.0))
    em.create_link(11, 0, 0.0, LinkKind.LOOP)
    em.create_link(5, 0, 0.0, LinkKind.LOOP)
    em.relax()
    src, dst, t, _, _, _ = em.links
    n, k = em.count, em.link_count
    yaw = em.poses[src, 3]
    meas = np.stack(
        [np.cos(yaw) * t[:, 0] - np.sin(yaw) * t[:, 1], np.sin(yaw) * t[:, 0] + np.cos(yaw) * t[:, 1], t[:, 2]], axis=1
    )
    a = np.zeros((k + 1, n))
    a[np.arange(k), dst] = 1.0
    a[np.arange(k), src] = -1.0
    a[k, :] = 1.0  # gauge: fix the centroid to the relaxed one
    centroid = em.poses[:, :3].mean(axis=0)
    b = np.vstack([meas, centroid * n])
    solution, *_ = np.linalg.lstsq(a, b, rcond=None)
    assert np.allclose(em.poses[:, :3], solution, atol=1e-6)


def test_correction_step_clamp_limits_each_iteration() -> None:
    em = _em(exp_loops=1, max_correction_step=0.05, exp_relax_tolerance=0.0)
    em.create_experience(0, np.zeros(3), 0.0, 0)
    em.on_odo(Motion(10.0, 0.0, 0.0, 0.0, 1.0))
    em.create_experience(1, np.zeros(3), 1.0, 0)
    em.add_link_raw(1, 0, np.array([-9.0, 0.0, 0.0, 0.0]), 1.0, 9.0, LinkKind.MANUAL)  # 1 m inconsistent
    before = em.poses.copy()
    em.relax(iterations=1)
    moved = np.linalg.norm(em.poses[:, :3] - before[:, :3], axis=1)
    assert moved.max() == pytest.approx(0.05)


def test_snapshot_restore_round_trip() -> None:
    em = _em()
    em.create_experience(0, np.array([1.0, 2.0, 3.0]), 0.5, 3)
    em.on_odo(Motion(1.0, 0.5, 0.2, 0.3, 1.0))
    em.create_experience(2, np.array([4.0, 5.0, 6.0]), 1.5, 3)
    em.on_odo(Motion(0.5, 0.0, 0.0, 0.0, 0.5))
    snap = em.snapshot()
    back = ExperienceMap.restore(em.params, 3, snap).snapshot()
    assert snap.keys() == back.keys()
    for key in snap:
        assert np.array_equal(snap[key], back[key]), key
    assert ExperienceMap.restore(em.params, 3, snap).experiences_of_template(2) == [1]


def test_a_relocalisation_keeps_the_robots_own_odometry_between_the_experiences_it_created() -> None:
    """Reckoning links: from the last experience created to the next, whatever loop closure came between."""
    em = _em()
    em.create_experience(0, np.zeros(3), 0.0, 0)
    em.on_odo(Motion(2.0, 0.0, 0.0, 0.0, 1.0))
    em.create_experience(1, np.zeros(3), 1.0, 0)  # no relocalisation since 0: nothing kept
    assert em.snapshot()["em_reckon_from"].size == 0
    em.on_odo(Motion(1.0, 0.0, 0.0, math.pi / 2, 1.0))  # 1 m ahead, then a left turn
    em.create_link(em.current, 0, 0.0, LinkKind.LOOP)
    em.set_experience(0, 0.0)  # relocalised onto 0 (facing 0 again)
    em.on_odo(Motion(3.0, 0.0, 0.0, 0.0, 2.0))  # 3 m ahead: +y in 1's frame, +x in 0's
    e2 = em.create_experience(2, np.zeros(3), 4.0, 0)
    state = em.snapshot()
    assert state["em_reckon_from"].tolist() == [1] and state["em_reckon_to"].tolist() == [e2]
    assert state["em_reckon_link"][0] == pytest.approx([1.0, 3.0, 0.0, math.pi / 2, 3.0, 4.0])
    src, dst, transform, _, _, _ = em.links
    assert (int(src[-1]), int(dst[-1])) == (0, e2) and transform[-1] == pytest.approx([3.0, 0.0, 0.0, 0.0])
    assert state["em_last_created"] == e2 and not state["em_reckon"].any()
    again = ExperienceMap.restore(em.params, 3, state)
    assert all(np.array_equal(v, again.snapshot()[k]) for k, v in state.items())


@pytest.mark.parametrize(
    ("kind", "changes", "joint"),
    [
        (LinkKind.LOOP, {}, False),  # a single session's map: RatSLAM's fixed point, as OpenRatSLAM
        (LinkKind.MERGE, {}, True),  # a merged map: the joint least squares (merge_relax_joint, default on)
        (LinkKind.MERGE, {"merge_relax_joint": False}, False),
        (LinkKind.LOOP, {"exp_relax_joint": True}, True),  # every map
    ],
)
def test_a_map_holding_a_merge_link_is_settled_on_the_joint_least_squares(
    kind: LinkKind, changes: dict[str, bool], joint: bool
) -> None:
    em = _em(**changes)
    for k in range(3):
        em.create_experience(k, np.array([float(k), 0.0, 0.0]), float(k), 0)
    assert not em.joint or changes.get("exp_relax_joint", False)  # no merge link yet
    assert em.add_link_raw(2, 0, np.array([-2.0, 0.0, 0.0, 0.0]), 1.0, 2.0, kind)
    assert em.joint is joint


@pytest.mark.parametrize(
    ("origins", "changes", "joint"),
    [
        ((0, 0, 0), {}, False),  # one session: RatSLAM's fixed point
        ((1, 1, 0), {}, True),  # a merge identified the partial map's experiences: merged, though no merge link
        ((1, 1, 0), {"merge_relax_joint": False}, False),
    ],
)
def test_a_map_holding_experiences_of_two_sessions_is_settled_on_the_joint_least_squares(
    origins: tuple[int, ...], changes: dict[str, bool], joint: bool
) -> None:
    em = _em(**changes)
    for k, origin in enumerate(origins):
        em.create_experience(k, np.array([float(k), 0.0, 0.0]), float(k), origin)
    assert em.add_link_raw(2, 0, np.array([-2.0, 0.0, 0.0, 0.0]), 1.0, 2.0, LinkKind.LOOP)
    assert em.joint is joint

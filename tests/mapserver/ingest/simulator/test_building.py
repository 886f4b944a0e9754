"""The ``building`` and ``terrain`` scenarios: storeys at distinct heights, a ramp between, look-alike floors, z."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapserver.errors import InputError
from mapserver.ingest.simulator import plan_scenario, render, simulate_session
from mapserver.ingest.simulator.building import STAIRWELL_WALL_M
from mapserver.ingest.simulator.render import surface_hits

STOREY = 3.0


def _drive(name: str, session: str, seed: int = 2, **params: float):  # type: ignore[no-untyped-def]
    plan = plan_scenario(name, seed, params=params)
    index, spec = next((i, s) for i, s in enumerate(plan.sessions) if s.name == session)
    return plan, simulate_session(plan, spec, index, seed)


def test_same_seed_same_building_other_seed_other_textures() -> None:
    a, b, c = (plan_scenario("building", s) for s in (4, 4, 5))
    for field in ("p0", "p1", "base", "top", "tex_offset", "tex_flat"):
        assert np.array_equal(getattr(a.world, field), getattr(b.world, field)), field
    assert not np.array_equal(a.world.tex_flat[: c.world.tex_flat.size], c.world.tex_flat[: a.world.tex_flat.size])
    one = simulate_session(a, a.sessions[0], 0, 4)
    two = simulate_session(b, b.sessions[0], 0, 4)
    assert np.array_equal(one.true_poses, two.true_poses) and np.array_equal(one.odom_poses, two.odom_poses)


def test_storey_two_is_storey_one_raised_with_a_share_of_new_textures() -> None:
    plan = plan_scenario("building", 3)
    w, floors = plan.world, plan.info["floors"]
    n = floors["surfaces_per_floor"]
    one, two = np.arange(n), np.arange(n, 2 * n)
    assert np.array_equal(w.p0[one], w.p0[two]) and np.array_equal(w.p1[one], w.p1[two])  # the same plan
    assert np.array_equal(w.base[two], w.base[one] + STOREY) and np.array_equal(w.top[two], w.top[one] + STOREY)
    assert w.base[one].min() == 0.0 and w.top[one].max() == STOREY  # storey 1 stays below storey 2
    changed = w.tex_offset[one] != w.tex_offset[two]
    assert changed.sum() == floors["restyled"] == round(0.3 * n)
    # the stairwell: the rest of the surfaces, two storeys tall, around the ramp
    rest = np.arange(2 * n, w.count)
    assert rest.size > 0 and np.all(w.base[rest] == 0.0) and np.all(w.top[rest] == 2 * STOREY)
    mid = 0.5 * (w.p0[rest] + w.p1[rest])
    radius = np.hypot(mid[:, 0] - floors["ramp_centre"][0], mid[:, 1] - floors["ramp_centre"][1])
    r = floors["ramp_radius_m"]
    assert radius.max() < r + STAIRWELL_WALL_M + 0.01 and radius.min() > r - STAIRWELL_WALL_M - 0.05  # chords


def test_single_drives_storey_one_the_ramp_then_storey_two_with_odometry_in_z() -> None:
    plan, drive = _drive("building", "single")
    floors = plan.info["floors"]
    z = drive.true_poses[:, 2]
    assert z[0] == 0.0 and z[-1] == STOREY
    assert np.all(np.diff(z) >= -1e-12)  # it climbs once and never comes down
    between = (z > 0.0) & (z < STOREY)
    centre = np.asarray(floors["ramp_centre"])
    on_ramp = np.hypot(*(drive.true_poses[between, :2] - centre).T)
    assert np.all(np.abs(on_ramp - floors["ramp_radius_m"]) < 0.5)  # between the storeys only on the ramp
    # laps on each storey over the same plan: every storey-2 position lies over storey 1's route
    low, high = drive.true_poses[z == 0.0, :2], drive.true_poses[z == STOREY, :2]
    gap = np.min(np.linalg.norm(high[::10, None, :] - low[None, ::5, :], axis=2), axis=1)
    assert gap.max() < 0.6
    assert len(high) > 1.8 * 10 * floors["lap_length_m"] / plan.params["speed"]  # about two laps up there
    # the odometry's z follows the climb (with its vertical-speed bias and noise)
    dz = drive.odom_poses[-1, 2] - drive.odom_poses[0, 2]
    assert abs(dz - STOREY) < 1.5 and dz != STOREY
    assert drive.errors["vz_bias"] == pytest.approx(0.003)


def test_the_partial_sessions_cover_one_storey_each_and_the_ramp() -> None:
    for session, heights in (("floor1", {0.0}), ("floor2", {STOREY})):
        _, drive = _drive("building", session)
        assert set(np.unique(drive.true_poses[:, 2]).tolist()) == heights
    _, stairs = _drive("building", "stairs")
    z = stairs.true_poses[:, 2]
    assert z[0] == 0.0 and z[-1] == STOREY and 0.2 < np.mean(z == 0.0) < 0.6


def _image(plan, x: float, y: float, z: float, yaw: float) -> np.ndarray:  # type: ignore[no-untyped-def]
    return render(plan.world, plan.camera, x, y, z, yaw)


def test_views_of_the_two_storeys_look_alike_but_differ_in_their_details() -> None:
    plan = plan_scenario("building", 3)
    same = plan_scenario("building", 3, params={"restyle": 0.0})
    pose = (4.0, 5.0, math.pi)  # the north corridor heading west, the stairwell out of sight
    low, high = _image(plan, *pose[:2], 0.0, pose[2]), _image(plan, *pose[:2], STOREY, pose[2])
    # without restyled surfaces the storeys look the same; with them, alike (correlated) but not the same
    alike = _image(same, *pose[:2], 0.0, pose[2]) - _image(same, *pose[:2], STOREY, pose[2])
    assert np.abs(alike).max() < 1e-12  # (heights differ in rounding only)
    corr = np.corrcoef(low.ravel(), high.ravel())[0, 1]
    assert 0.3 < corr < 0.999 and np.mean(np.abs(low - high)) > 0.01
    elsewhere = _image(plan, -4.0, -5.0, 0.0, 0.0)
    assert np.mean(np.abs(low - high)) < np.mean(np.abs(low - elsewhere))


def test_a_camera_sees_only_its_own_storey() -> None:
    plan = plan_scenario("building", 3)
    n = plan.info["floors"]["surfaces_per_floor"]
    cam = plan.camera
    for z, storey in ((0.0, range(n)), (STOREY, range(n, 2 * n))):
        lo, hi = plan.world.band(z)[2:]
        hits = surface_hits(plan.world, 4.0, 5.0, z + cam.mount_height, cam.azimuths, cam.slopes, cam.max_range,
                            (lo, hi))  # fmt: skip
        seen = set(hits.surface.tolist())
        assert seen and seen <= set(storey) | set(range(2 * n, plan.world.count))


def test_terrain_follows_its_hills_and_is_deterministic() -> None:
    plan, drive = _drive("terrain", "single", seed=6)
    again = simulate_session(plan_scenario("terrain", 6), plan.sessions[0], 0, 6)
    assert np.array_equal(drive.true_poses, again.true_poses)
    z = drive.true_poses[:, 2]
    assert z.max() - z.min() > 1.0 and plan.preset == "neuroslam"
    flat = plan_scenario("terrain", 6, params={"hill_m": 0.0})
    assert np.all(flat.world.base == -0.3)  # walls stand 0.3 m into the ground; on hills they stand higher
    assert plan.world.base.max() > 0.0 and plan.world.local_floor


def test_bad_building_parameters_are_input_errors() -> None:
    for params in ({"laps": 1.5}, {"restyle": 2.0}, {"storey_m": 1.0}, {"ramp_radius_m": 1.0}, {"width_m": 5.0}):
        with pytest.raises(InputError):
            plan_scenario("building", params=params)
    with pytest.raises(InputError, match="fov_deg"):
        plan_scenario("terrain", params={"fov_deg": 200.0})

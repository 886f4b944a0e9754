"""merge_states on small hand-built snapshots: counts, ids, the lattice shift, the rigid transform, links."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core import Engine, LinkKind, Motion, Params
from core.se3 import compose, inverse, relative
from mapserver.errors import MergeError
from mapserver.merge import LatticeTransform, Match, MergeRecord, merge_states, restore_merged
from mapserver.merge.lattice import wrap_coords
from mapserver.merge.provenance import match_from_dict, match_to_dict
from mapserver.merge.snapshot import OPTIONAL_SNAPSHOT_KEYS, SNAPSHOT_KEYS
from tests.mapserver.merge.snapshots import TX, TY, make_state

DIMS = (21, 21, 36)
T_TRUE = np.array([3.0, -2.0, 0.5, 0.7])  # partial map frame → loaded map frame


def loaded_state() -> dict[str, np.ndarray]:
    """Six experiences along the world x axis, 1 m apart, heading 0; lattice (5 + x, 10, 0)."""
    x = np.arange(6.0)
    poses = np.stack([x, np.zeros(6), np.zeros(6), np.zeros(6)], axis=1)
    pcs = np.stack([5.0 + x, np.full(6, 10.0), np.zeros(6)], axis=1)
    return make_state(poses, pcs, DIMS, origin=1, seed=1)


def partial_state(
    f_true: LatticeTransform, world_x: tuple[float, ...] = (-1.0, 0.0, 1.0, 2.0), **kwargs: object
) -> dict[str, np.ndarray]:
    """The same road seen by another session: poses in a frame moved by T_TRUE, lattice by f_true⁻¹."""
    x = np.asarray(world_x)
    n = x.size
    world = np.stack([x, np.zeros(n), np.zeros(n), np.zeros(n)], axis=1)
    poses = compose(inverse(T_TRUE), world)
    equivalent = np.stack([5.0 + x, np.full(n, 10.0), np.zeros(n)], axis=1)  # loaded lattice of those places
    pcs = f_true.inverse().apply(equivalent)
    return make_state(poses, pcs, DIMS, origin=2, seed=2, **kwargs)  # type: ignore[arg-type]


SHIFT = LatticeTransform.between(DIMS, source=(2.0, 17.0, 0.0), target=(7.0, 10.0, 0.0))  # Δθ = 0
TURN = LatticeTransform.between(DIMS, source=(12.0, 3.0, 27.0), target=(7.0, 10.0, 0.0))  # Δθ = +9 = 90°


@pytest.mark.parametrize("f_true", [SHIFT, TURN], ids=["translation", "90deg"])
def test_paper_case_counts_ids_and_geometry(f_true: LatticeTransform) -> None:
    loaded, partial = loaded_state(), partial_state(f_true)
    match = Match.at_experience(partial, 3, stored_template=2, stored_experience=2)
    state, record = merge_states(loaded, partial, match)

    # (i) templates = L + P − 1, partial ids appended in order, the matched one → the stored one
    assert state["lv_templates"].shape == (9, TY, TX)
    assert record.template_map.tolist() == [6, 7, 8, 2]
    assert np.array_equal(state["lv_templates"][6:], partial["lv_templates"][:3])
    assert state["lv_origin"].tolist() == [1] * 6 + [2] * 3
    # experiences = E_l + E_p − 1, the matched partial experience identified with the stored one
    assert record.experience_map.tolist() == [6, 7, 8, 2]
    assert state["em_template"].tolist() == [0, 1, 2, 3, 4, 5, 6, 7, 8]
    assert state["em_origin"].tolist() == [1] * 6 + [2] * 3
    # (iv) poses: the rigid transform recovers the true places exactly; the matched pair coincides
    assert record.transform == pytest.approx(T_TRUE)
    assert state["em_pose"][6:] == pytest.approx(np.array([[-1.0, 0, 0, 0], [0, 0, 0, 0], [1, 0, 0, 0]]), abs=1e-12)
    assert compose(np.asarray(record.transform), partial["em_pose"][3]) == pytest.approx(loaded["em_pose"][2])
    # (iii) lattice: every partial link and experience lands on the loaded lattice's cell for that place
    assert record.lattice_offset == pytest.approx(f_true.offset)
    expected_pc = [[4.0, 10.0, 0.0], [5.0, 10.0, 0.0], [6.0, 10.0, 0.0]]
    assert state["em_pc"][6:] == pytest.approx(np.array(expected_pc), abs=1e-9)
    assert state["pc_link_template"].tolist() == [0, 1, 2, 3, 4, 5, 6, 7, 8]
    assert state["pc_link_coords"][6:] == pytest.approx(np.array(expected_pc), abs=1e-9)
    # links: L + P, relative transforms kept, the link into the matched experience is the merge link (Eq. 17)
    assert state["em_link_from"].tolist() == [0, 1, 2, 3, 4, 6, 7, 8]
    assert state["em_link_to"].tolist() == [1, 2, 3, 4, 5, 7, 8, 2]
    assert state["em_link_kind"].tolist() == [0] * 7 + [int(LinkKind.MERGE)]
    assert record.merge_links.tolist() == [7]  # merge links come last
    assert np.array_equal(state["em_link_transform"][5:], partial["em_link_transform"])
    # the robot continues at the stored experience, facing the loaded frame's heading
    assert int(state["em_current"]) == 2 and int(state["em_previous"]) == 8
    assert int(state["lv_current"]) == 2 and int(state["pc_current_vt"]) == 2
    assert state["em_accum"][3] == pytest.approx(0.0, abs=1e-12)
    assert state["pc_best"] == pytest.approx([7.0, 10.0, 0.0])
    assert state["gate_history"][-3:].tolist() == [2, 2, 2]
    assert bool(state["em_relax_pending"])
    assert (record.templates, record.experiences, record.links) == (9, 9, 8)


def test_translation_only_shift_would_misplace_a_rotated_session() -> None:
    """The paper's Eq. 11 (shift only) puts the 90°-rotated partial links 1–3 cells off their places."""
    partial = partial_state(TURN)
    paper = wrap_coords(partial["pc_link_coords"][:3] + TURN.offset, DIMS)
    truth = np.array([[4.0, 10.0, 0.0], [5.0, 10.0, 0.0], [6.0, 10.0, 0.0]])
    errors = np.linalg.norm(paper[:, :2] - truth[:, :2], axis=1)
    assert errors == pytest.approx([3 * math.sqrt(2), 2 * math.sqrt(2), math.sqrt(2)])


def test_every_partial_link_is_shifted_by_the_offset_modulo_dims() -> None:
    rng = np.random.default_rng(5)
    loaded = loaded_state()
    partial = partial_state(SHIFT)
    partial["pc_link_coords"] = rng.uniform(0, 1, size=(4, 3)) * np.asarray(DIMS)  # anywhere on the torus
    match = Match.at_experience(partial, 3, stored_template=2, stored_experience=2)
    state, record = merge_states(loaded, partial, match)
    expected = np.mod(partial["pc_link_coords"][:3] + np.asarray(record.lattice_offset), DIMS)
    assert state["pc_link_coords"][6:] == pytest.approx(expected, abs=1e-9)
    assert record.lattice_offset == pytest.approx([5.0, -7.0, 0.0])


def test_disabled_shift_keeps_the_partial_lattice_but_moves_the_packet() -> None:
    loaded, partial = loaded_state(), partial_state(TURN)
    match = Match.at_experience(partial, 3, stored_template=2, stored_experience=2)
    state, record = merge_states(loaded, partial, match, shift_lattice=False)
    assert not record.lattice_shifted
    assert np.array_equal(state["pc_link_coords"][6:], partial["pc_link_coords"][:3])
    assert np.array_equal(state["em_pc"][6:], partial["em_pc"][:3])
    assert state["pc_best"] == pytest.approx([7.0, 10.0, 0.0])  # operation (ii) still happens
    assert state["em_pose"][6:] == pytest.approx(np.array([[-1.0, 0, 0, 0], [0, 0, 0, 0], [1, 0, 0, 0]]), abs=1e-12)


def test_odometry_since_the_current_experience_is_carried_into_the_loaded_frame() -> None:
    accum = np.array([0.3, -0.1, 0.05, -0.7 + 0.2, 1.5, 0.4])  # partial frame (yaw −0.7 there): moved, turned 0.2
    partial = partial_state(SHIFT, accum=accum)
    match = Match.at_experience(partial, 3, stored_template=2, stored_experience=2)
    state, record = merge_states(loaded_state(), partial, match)
    c, s = math.cos(0.7), math.sin(0.7)
    assert state["em_accum"] == pytest.approx([c * 0.3 + s * 0.1, s * 0.3 - c * 0.1, 0.05, 0.2, 1.5, 0.4])
    assert record.transform[3] == pytest.approx(0.7)


def test_a_session_merged_before_its_first_experience_continues_where_its_odometry_took_it() -> None:
    """No partial experience yet (a motion gate held them): the robot is T ⊕ its odometry so far, from e_u.

    Hand-computed: the anchor view was seen at (0.1, 0, 0, 0.3) in the session frame and matches stored
    experience 2 at (2, 0, 0, 0), so T = (2 − 0.1·cos 0.3, 0.1·sin 0.3, 0, −0.3); since the session start the
    robot went to (0.4, 0.2, 0, 0.5), i.e. to T ⊕ that = T's position + R(−0.3)(0.4, 0.2), heading 0.2. Put on
    e_u itself facing e_u's way, it would be 0.36 m and 11° off here (on ``cave3d`` seed 0 35° off).
    """
    partial = partial_state(SHIFT, world_x=(1.0,), accum=np.array([0.4, 0.2, 0.0, 0.5, 2.0, 0.45]))
    for key in ("em_pose", "em_pc", "em_template", "em_stamp", "em_origin"):
        partial[key] = partial[key][:0]
    partial["em_current"], partial["em_previous"] = np.asarray(-1), np.asarray(-1)
    match = Match(
        stored_template=2, stored_experience=2, partial_template=0, partial_pose=(0.1, 0.0, 0.0, 0.3),
        partial_packet=tuple(float(v) for v in partial["pc_best"]), relative_rad=0.0,
    )  # fmt: skip
    state, record = merge_states(loaded_state(), partial, match)
    c, s = math.cos(0.3), math.sin(0.3)
    assert record.transform == pytest.approx([2.0 - 0.1 * c, 0.1 * s, 0.0, -0.3])
    robot = (2.0 - 0.1 * c + c * 0.4 + s * 0.2, 0.1 * s - s * 0.4 + c * 0.2)
    assert int(state["em_current"]) == 2 and int(state["em_previous"]) == -1
    assert state["em_accum"] == pytest.approx([robot[0] - 2.0, robot[1], 0.0, 0.2, 2.0, 0.45])


def test_confirmation_pairs_are_identified_too() -> None:
    """Partial copies of stored views seen while confirming are not duplicated."""
    loaded, partial = loaded_state(), partial_state(SHIFT)
    match = Match.at_experience(partial, 3, stored_template=2, stored_experience=2, pairs=((1, 0), (2, 1), (3, 2)))
    state, record = merge_states(loaded, partial, match)
    assert record.template_map.tolist() == [6, 0, 1, 2]
    assert record.experience_map.tolist() == [6, 0, 1, 2]
    assert record.templates == 7 and record.experiences == 7
    # partial links 1→2 and 2→3 became 0→1 and 1→2: duplicates of stored links, dropped; 0→1 joins: merge link
    assert state["em_link_from"][5:].tolist() == [6] and state["em_link_to"][5:].tolist() == [0]
    assert state["em_link_kind"][5] == int(LinkKind.MERGE)


def test_known_start_leaves_the_stored_map_as_it_was() -> None:
    """A session whose whole partial map lies in the confirmation window: merged = stored, robot placed."""
    loaded = loaded_state()
    partial = partial_state(SHIFT, world_x=(1.0, 2.0))
    match = Match.at_experience(partial, 1, stored_template=2, stored_experience=2, pairs=((0, 1), (1, 2)))
    state, record = merge_states(loaded, partial, match)
    for key in ("lv_templates", "em_pose", "em_pc", "em_link_from", "em_link_to", "pc_link_coords"):
        assert np.array_equal(state[key], loaded[key]), key
    assert int(state["em_current"]) == 2 and int(state["em_previous"]) == 1
    assert record.merge_links.size == 0


def test_without_an_identified_experience_a_merge_link_joins_the_graphs() -> None:
    """Matched partial template without an experience (gates): Eq. 17 from the current experience to e_u."""
    loaded = loaded_state()
    partial = partial_state(SHIFT, world_x=(-1.0, 0.0, 1.0), n_templates=4)
    robot = compose(inverse(T_TRUE), np.array([2.0, 0.0, 0.0, 0.0]))
    match = Match(
        stored_template=2, stored_experience=2, partial_template=3, partial_pose=tuple(robot),
        partial_packet=tuple(SHIFT.source),
    )
    state, record = merge_states(loaded, partial, match)
    assert record.experience_map.tolist() == [6, 7, 8]
    assert record.merge_links.tolist() == [7]
    assert (int(state["em_link_from"][7]), int(state["em_link_to"][7])) == (8, 2)
    link = state["em_link_transform"][7]
    assert link == pytest.approx([1.0, 0.0, 0.0, 0.0], abs=1e-12)  # 1 m ahead, as the places are
    assert compose(state["em_pose"][8], link) == pytest.approx(state["em_pose"][2], abs=1e-12)


def test_output_has_exactly_the_documented_keys_and_restores() -> None:
    params = Params().replace(template_x_size=TX, template_y_size=TY, pc_dim_xy=21, pc_dim_th=36, vt_shift_match=1)
    loaded, partial = loaded_state(), partial_state(TURN)
    loaded["eng_future_cache"] = np.zeros(3)  # an optional key someone may add: not carried
    state, _ = merge_states(loaded, partial, Match.at_experience(partial, 3, stored_template=2, stored_experience=2))
    assert set(state) == set(SNAPSHOT_KEYS) | set(OPTIONAL_SNAPSHOT_KEYS)
    assert state["em_link_active"].tolist() == [True] * state["em_link_from"].size
    assert state["lv_templates"].dtype == np.float32 and state["em_link_kind"].dtype == np.int8
    assert state["em_template"].dtype == np.int64 and state["em_pose"].dtype == np.float64
    engine = Engine.restore(params, state, origin=2)
    assert engine.experience_count == 9 and engine.template_count == 9
    assert engine.map.experiences_of_template(2) == [2]
    image = np.full((TY * 4, TX * 4), 128, dtype=np.uint8)
    engine.step(image, Motion(0.5, 0.0, 0.0, 0.0, 1.0), 300.0)  # mapping continues
    assert engine.frames == int(partial["eng_frames"]) + 1


def test_record_round_trips_through_json() -> None:
    loaded, partial = loaded_state(), partial_state(TURN)
    _, record = merge_states(loaded, partial, Match.at_experience(partial, 3, stored_template=2, stored_experience=2))
    data = json.loads(json.dumps(record.to_dict()))
    again = MergeRecord.from_dict(data)
    assert again.transform == pytest.approx(record.transform)
    assert np.array_equal(again.experience_map, record.experience_map)
    assert np.asarray(data["matrix"]) == pytest.approx(record.matrix)
    assert data["heading_offset_rad"] == pytest.approx(math.pi / 2)


def test_incompatible_maps_are_refused() -> None:
    loaded, partial = loaded_state(), partial_state(SHIFT)
    match = Match.at_experience(partial, 3, stored_template=2, stored_experience=2)
    other = dict(partial, pc_activity=np.zeros((15, 15, 36)))
    with pytest.raises(MergeError, match="lattices differ"):
        merge_states(loaded, other, match)
    other = dict(partial, lv_templates=np.zeros((4, 5, 5), dtype=np.float32))
    with pytest.raises(MergeError, match="template sizes differ"):
        merge_states(loaded, other, match)
    with pytest.raises(MergeError, match="stored template 6 is out of range"):
        merge_states(loaded, partial, Match.at_experience(partial, 3, stored_template=6, stored_experience=2))
    missing = {k: v for k, v in partial.items() if k != "em_accum"}
    with pytest.raises(MergeError, match="lacks em_accum"):
        merge_states(loaded, missing, match)


@settings(max_examples=25, deadline=None)
@given(
    st.tuples(st.floats(-20, 20), st.floats(-20, 20), st.floats(-2, 2), st.floats(-math.pi, math.pi)),
    st.integers(3, 8),
    st.integers(0, 2**16),
)
def test_rigid_merge_invariants(t_true: tuple[float, ...], n: int, seed: int) -> None:
    """Any partial frame: pairwise distances kept, the matched pair coincides, links kept verbatim."""
    rng = np.random.default_rng(seed)
    loaded = loaded_state()
    steps = np.column_stack([rng.uniform(0.5, 1.5, n), rng.uniform(-0.3, 0.3, n), rng.uniform(-0.2, 0.2, n),
                             rng.uniform(-0.5, 0.5, n)])
    poses = np.zeros((n, 4))
    for i in range(1, n):
        poses[i] = compose(poses[i - 1], steps[i])
    pcs = rng.uniform(0, 1, size=(n, 3)) * np.asarray(DIMS)
    partial = make_state(compose(np.asarray(t_true), poses), pcs, DIMS, origin=2, seed=seed)
    match = Match.at_experience(partial, n - 1, stored_template=4, stored_experience=4)
    state, record = merge_states(loaded, partial, match)
    moved = state["em_pose"][6:]
    before = np.linalg.norm(partial["em_pose"][: n - 1, None, :3] - partial["em_pose"][None, : n - 1, :3], axis=2)
    after = np.linalg.norm(moved[:, None, :3] - moved[None, :, :3], axis=2)
    assert after == pytest.approx(before, abs=1e-8)
    assert compose(np.asarray(record.transform), partial["em_pose"][n - 1]) == pytest.approx(loaded["em_pose"][4])
    # every kept link's transform is still the relative pose of its (moved) ends: residual 0
    src, dst = state["em_link_from"][5:], state["em_link_to"][5:]
    residual = relative(state["em_pose"][src], state["em_pose"][dst]) - state["em_link_transform"][5:]
    assert np.abs(residual[:, :3]).max() == pytest.approx(0.0, abs=1e-8)
    assert record.templates == 6 + n - 1 and record.experiences == 6 + n - 1 and record.links == 5 + n - 1


def test_restore_merged_schedules_relaxation_at_the_merge_links() -> None:
    params = Params().replace(template_x_size=TX, template_y_size=TY, pc_dim_xy=21, pc_dim_th=36)
    loaded, partial = loaded_state(), partial_state(SHIFT)
    # the partial robot's pose is 0.2 m off: the redirected link does not close exactly
    match = Match.at_experience(partial, 3, stored_template=2, stored_experience=2, pairs=((1, 1),))
    state, record = merge_states(loaded, partial, match, identify_within=1.0)
    tail = record.merge_links
    assert tail.tolist() == list(range(record.links - tail.size, record.links))
    engine = restore_merged(params, state, record, origin=2)
    snap = engine.map.snapshot()
    for key in ("em_link_from", "em_link_to", "em_link_transform", "em_link_kind", "em_pose"):
        assert np.array_equal(snap[key], state[key]), key
    queued = set(engine.map.relax_queue.tolist())
    ends = set(state["em_link_from"][tail].tolist()) | set(state["em_link_to"][tail].tolist())
    assert ends <= queued and len(queued) < engine.experience_count


def test_merged_maps_keep_the_link_flags_of_both_maps() -> None:
    loaded, partial = loaded_state(), partial_state(TURN)
    loaded["em_link_active"] = np.arange(loaded["em_link_from"].size) % 2 == 0  # every other link switched off
    partial["em_link_active"] = np.zeros(partial["em_link_from"].size, dtype=bool)  # all off
    state, _ = merge_states(loaded, partial, Match.at_experience(partial, 3, stored_template=2, stored_experience=2))
    n_loaded = loaded["em_link_from"].size
    assert state["em_link_active"][:n_loaded].tolist() == loaded["em_link_active"].tolist()
    kinds = state["em_link_kind"][n_loaded:]
    # the partial's kept links stay off; the links that join the graphs (merge links), all off, start on
    assert state["em_link_active"][n_loaded:].tolist() == (kinds == 2).tolist()
    assert (kinds == 2).any() and (kinds != 2).any()


def test_a_link_its_own_map_switched_off_stays_off_as_a_merge_link_and_through_the_restored_engine() -> None:
    """The partial's links 2 → 3 (odometry) and 3 → 4 join the graphs once its experience 3 is identified with the
    loaded 2; 2 → 3 was switched off by the partial's robust check (a false relocalisation's odometry link):
    it stays off, 3 → 4 stays on, and the restored engine holds the same statuses (it re-adds merge links)."""
    params = Params().replace(template_x_size=TX, template_y_size=TY, pc_dim_xy=21, pc_dim_th=36)
    loaded, partial = loaded_state(), partial_state(SHIFT, world_x=(-1.0, 0.0, 1.0, 2.0, 3.0))
    p_from, p_to = partial["em_link_from"], partial["em_link_to"]
    switched_off = (p_from == 2) & (p_to == 3)
    assert switched_off.sum() == 1 and ((p_from == 3) & (p_to == 4)).sum() == 1
    partial["em_link_active"] = ~switched_off
    match = Match.at_experience(partial, 3, stored_template=2, stored_experience=2)
    state, record = merge_states(loaded, partial, match)
    tail = record.merge_links
    ends = list(zip(state["em_link_from"][tail].tolist(), state["em_link_to"][tail].tolist(), strict=True))
    statuses = dict(zip(ends, state["em_link_active"][tail].tolist(), strict=True))
    n_loaded = loaded["em_pose"].shape[0]
    assert statuses == {(n_loaded + 2, 2): False, (2, n_loaded + 3): True}  # partial 4 is merged 6 + 3
    engine = restore_merged(params, state, record, origin=2)
    assert np.array_equal(engine.map.snapshot()["em_link_active"], state["em_link_active"])


def test_reckoning_links_are_renumbered_an_identified_end_to_the_stored_experience() -> None:
    """The partial's experiences 0, 1, 2 become 6, 7, 8 and its 3 is identified with the loaded 2: its reckoning
    link 3 → 1 becomes 2 → 7 (until 2026-11-28 it was dropped, and the relocalisation's odometry link it stood
    in for, switched off in the partial map, became a link the robust check could not switch off); 1 → 3, into
    the identified experience, is dropped (the odometry link into the loaded 2 is the loaded map's own)."""
    loaded, partial = loaded_state(), partial_state(TURN)
    loaded.update(em_reckon_from=np.array([4]), em_reckon_to=np.array([5]), em_reckon_link=np.full((1, 6), 9.0))
    rows = np.arange(18, dtype=np.float64).reshape(3, 6)
    partial.update(em_reckon_from=np.array([0, 1, 3]), em_reckon_to=np.array([2, 3, 1]), em_reckon_link=rows,
                   em_reckon=np.arange(6, dtype=np.float64), em_last_created=np.asarray(2))  # fmt: skip
    match = Match.at_experience(partial, 3, stored_template=2, stored_experience=2)
    state, record = merge_states(loaded, partial, match)
    assert record.experience_map.tolist() == [6, 7, 8, 2]
    assert state["em_reckon_from"].tolist() == [4, 6, 2] and state["em_reckon_to"].tolist() == [5, 8, 7]
    assert state["em_reckon_link"].tolist() == [[9.0] * 6, rows[0].tolist(), rows[2].tolist()]  # source frame: kept
    assert state["em_reckon"].tolist() == list(range(6)) and int(state["em_last_created"]) == 8
    plain, _ = merge_states(loaded_state(), partial_state(TURN), match)
    assert plain["em_reckon_from"].size == 0 and int(plain["em_last_created"]) == -1  # states without them


def test_each_moved_experience_carries_its_lattice_distance_from_the_merge_anchor() -> None:
    """Operation (iii)'s lever arms: the anchor is partial experience 3 (loaded lattice (7, 10, 0)); the kept
    partial experiences 0, 1, 2 land at (4, 10, 0), (5, 10, 0), (6, 10, 0), so 3, 2 and 1 cells from it — in
    the partial lattice too, which the merge turned by 90° (a rotation keeps distances). Levers add up over
    successive merges; the loaded map's stay; with operation (iii) skipped nothing moved."""
    match_args = {"stored_template": 2, "stored_experience": 2}
    partial = partial_state(TURN)
    state, record = merge_states(loaded_state(), partial, Match.at_experience(partial, 3, **match_args))
    assert record.experience_map.tolist() == [6, 7, 8, 2]
    assert state["em_pc_lever"] == pytest.approx([0.0] * 6 + [3.0, 2.0, 1.0], abs=1e-9)
    loaded, again = loaded_state(), partial_state(TURN)
    loaded["em_pc_lever"] = np.full(6, 0.25)
    again["em_pc_lever"] = np.array([0.5, 1.0, 1.5, 2.0])
    state, _ = merge_states(loaded, again, Match.at_experience(again, 3, **match_args))
    assert state["em_pc_lever"] == pytest.approx([0.25] * 6 + [3.5, 3.0, 2.5], abs=1e-9)
    plain, _ = merge_states(loaded, again, Match.at_experience(again, 3, **match_args), shift_lattice=False)
    assert plain["em_pc_lever"] == pytest.approx([0.25] * 6 + [0.5, 1.0, 1.5], abs=1e-9)


def test_a_lever_arm_is_the_wrapped_planar_distance_from_the_anchor_in_a_4dof_lattice() -> None:
    """Only (x, y) count (the merge rotates about the vertical axis; z and θ are only shifted), across the faces."""
    from mapserver.merge.states import _lever_arm

    f = LatticeTransform.between((21, 21, 9, 36), source=(2.0, 17.0, 4.0, 0.0), target=(7.0, 10.0, 1.0, 9.0))
    coords = np.array([[5.0, 17.0, 8.0, 30.0], [20.0, 17.0, 4.0, 0.0], [2.0, 1.0, 0.0, 5.0], [5.0, 13.0, 4.0, 0.0]])
    assert _lever_arm(f, coords) == pytest.approx([3.0, 3.0, 5.0, 5.0])
    assert _lever_arm(None, coords).tolist() == [0.0] * 4


def test_a_last_created_experience_identified_by_the_merge_starts_no_reckoning_link() -> None:
    """The partial's last created experience 3 is identified with the loaded 2: the merge, not the robot's
    odometry, joins what comes next to the loaded map, so no reckoning link may start there (it would join
    the sessions in the dead reckoning the robust check tests links against). Its pair: 2, kept, still starts one
    (the test above)."""
    loaded, partial = loaded_state(), partial_state(TURN)
    partial.update(em_reckon_from=np.zeros(0, np.int64), em_reckon_to=np.zeros(0, np.int64),
                   em_reckon_link=np.zeros((0, 6)), em_reckon=np.ones(6), em_last_created=np.asarray(3))  # fmt: skip
    match = Match.at_experience(partial, 3, stored_template=2, stored_experience=2)
    state, record = merge_states(loaded, partial, match)
    assert record.experience_map.tolist()[3] == 2
    assert int(state["em_last_created"]) == -1


def test_ties_join_a_drifted_copy_of_the_stored_ground_by_merge_links() -> None:
    """Each tie (``Match.ties``) whose partial experience is left apart becomes a merge link with its transform.

    Partial experiences at world x = −1, 0, 1 (not identified: no pair names their templates) and 2 (the anchor's,
    identified with the loaded experience there). The anchor's tie is left out (one node), as is the repeat of a
    pair (the first is kept).
    """
    loaded, partial = loaded_state(), partial_state(SHIFT)
    ties = ((1, 0, (-1.5, 0.0, 0.0, 0.0)), (1, 0, (0.0, 0.0, 0.0, 0.0)), (3, 2, (0.0, 0.0, 0.0, 0.0)),
            (2, 4, (2.0, 0.3, 0.0, 0.05)))  # fmt: skip
    match = dataclasses.replace(Match.at_experience(partial, 3, stored_template=2, stored_experience=2), ties=ties)
    state, record = merge_states(loaded, partial, match)
    assert record.experience_map.tolist() == [6, 7, 8, 2]
    added = slice(5, None)  # the loaded map's 5 odometry links come first
    pairs = list(zip(state["em_link_from"][added].tolist(), state["em_link_to"][added].tolist(), strict=True))
    assert pairs == [(6, 7), (7, 8), (8, 2), (7, 0), (8, 4)]
    assert state["em_link_kind"][added].tolist() == [int(LinkKind.ODOMETRY)] * 2 + [int(LinkKind.MERGE)] * 3
    assert state["em_link_transform"][8] == pytest.approx([-1.5, 0.0, 0.0, 0.0])
    assert state["em_link_transform"][9] == pytest.approx([2.0, 0.3, 0.0, 0.05])
    assert state["em_link_distance"][9] == pytest.approx(math.hypot(2.0, 0.3))
    assert state["em_link_active"][added].all()
    assert record.merge_links.tolist() == [7, 8, 9]
    without, _ = merge_states(loaded, partial, dataclasses.replace(match, ties=()))
    assert without["em_link_from"].size == 8  # the same merge but for the two ties
    for key in ("em_pose", "em_pc", "em_template"):  # ties add links only
        np.testing.assert_array_equal(state[key], without[key])


def test_a_tie_to_an_experience_the_maps_do_not_have_is_refused() -> None:
    """A tie naming a partial or stored experience out of range is a malformed match, not a silent skip."""
    loaded, partial = loaded_state(), partial_state(SHIFT)
    match = Match.at_experience(partial, 3, stored_template=2, stored_experience=2)
    with pytest.raises(MergeError, match="tied stored experience"):
        merge_states(loaded, partial, dataclasses.replace(match, ties=((1, 6, (0.0, 0.0, 0.0, 0.0)),)))
    with pytest.raises(MergeError, match="tied partial experience"):
        merge_states(loaded, partial, dataclasses.replace(match, ties=((4, 0, (0.0, 0.0, 0.0, 0.0)),)))


def test_a_match_and_its_ties_round_trip_through_the_event_json() -> None:
    """A redo rebuilds the merge from the stored match: its ties too; an event stored before ties has none."""
    match = dataclasses.replace(
        Match.at_experience(partial_state(SHIFT), 3, stored_template=2, stored_experience=2, pairs=((1, 0),)),
        ties=((1, 0, (0.1, -0.2, 0.0, 0.05)),),
    )
    data = json.loads(json.dumps(match_to_dict(match)))
    assert match_from_dict(data) == match
    del data["ties"]
    assert match_from_dict(data) == dataclasses.replace(match, ties=())


def test_merge_engine_keeps_the_stored_maps_templates_array_without_a_copy() -> None:
    """A stored map of 1,536 templates of 32 × 128 (24 MB in float32) merged with a running engine: the merged
    engine's templates are the stored map's array itself (read-only) and then the partial's kept ones, so
    merge_engine's traced peak is the merged engine's int32 fixed point (2,048 rows reserved, 32 MB), one block's
    quantising temporaries (8 MB each) and small arrays, not the float32 copies that joining the templates (24 MB)
    and restoring them (32 MB reserved) made.
    The templates and the fixed point equal those of the engine restored from merge_states' joined snapshot."""
    import tracemalloc

    from core.localview import LocalViewCells
    from mapserver.merge import StoredMap, merge_engine

    ty, tx = 32, 128
    params = Params().replace(template_x_size=tx, template_y_size=ty, pc_dim_xy=21, pc_dim_th=36, vt_shift_match=1)
    rng = np.random.default_rng(4)
    x = np.arange(6.0)
    poses = np.stack([x, np.zeros(6), np.zeros(6), np.zeros(6)], axis=1)
    pcs = np.stack([5.0 + x, np.full(6, 10.0), np.zeros(6)], axis=1)
    loaded = make_state(poses, pcs, DIMS, origin=1, seed=1, n_templates=1536)
    partial = partial_state(TURN)
    for state in (loaded, partial):
        views = rng.random((state["lv_means"].size, ty, tx), dtype=np.float32)
        state["lv_templates"], state["lv_means"] = views, views.reshape(views.shape[0], -1).mean(axis=1)
    match = Match.at_experience(partial, 3, stored_template=2, stored_experience=2)
    engine = Engine.restore(params, partial, origin=2)
    stored = StoredMap(1, params, loaded)
    tracemalloc.start()
    try:
        merged, record = merge_engine(stored, engine, match)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 32 * 2**20 + 2 * 8 * 2**20 + 4 * 2**20
    assert np.shares_memory(merged.local_view._templates.blocks[0], loaded["lv_templates"])
    joined = LocalViewCells.restore(params, merge_states(loaded, partial, match)[0])
    assert record.templates == merged.template_count == joined.count == 1539
    np.testing.assert_array_equal(merged.local_view.templates, joined.templates)
    np.testing.assert_array_equal(merged.local_view._fixed.view, joined._fixed.view)

"""The typed engine snapshot: bit-for-bit round trips through ``to_arrays``/``from_arrays`` and its key names."""

from __future__ import annotations

import numpy as np
import pytest

from core import Engine
from core.config import Params
from core.snapshot import EngineSnapshot, ExperienceMapSnapshot, MissingKeysError, PoseCellSnapshot
from tests.worlds import StripWorld


def _params() -> Params:
    return Params().replace(
        template_x_size=32, template_y_size=12, vt_shift_match=2, vt_step_match=1, vt_match_threshold=0.03,
        pc_dim_xy=21, pc_dim_th=36, pc_cell_x_size=1.0, exp_delta_pc_threshold=2.0, exp_loops=20,
        vt_min_inject_age=5, exp_initial_em_deg=0.0,
    )  # fmt: skip


def _assert_identical(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    assert list(a) == list(b)  # same keys, same order
    for key in a:
        assert a[key] is b[key], key  # the very arrays: nothing copied, nothing cast


def test_an_engine_snapshot_round_trips_bit_for_bit(strip_world: StripWorld) -> None:
    engine = Engine(_params())
    for img, motion, stamp in strip_world.drive(laps=1.2, yaw_bias=0.01):
        engine.step(img, motion, stamp)
    arrays = engine.snapshot()
    typed = EngineSnapshot.from_arrays(arrays)
    _assert_identical(typed.to_arrays(), arrays)
    assert typed.extra == {}  # every key of the continuous-attractor engine has its part
    assert typed.map.pose is arrays["em_pose"] and typed.pose_cells is not None
    assert typed.pose_cells.activity is arrays["pc_activity"]
    assert int(typed.counters.frames) == engine.frames > 0
    typed_now = engine.typed_snapshot()
    assert list(typed_now.to_arrays()) == list(arrays)
    for key, value in typed_now.to_arrays().items():
        assert np.array_equal(value, arrays[key], equal_nan=True) and value.dtype == arrays[key].dtype, key


def _minimal() -> dict[str, np.ndarray]:
    """A snapshot holding each required key once (values: their position), in a shuffled order."""
    keys = list(EngineSnapshot.required_keys())
    rng = np.random.default_rng(5)
    return {key: np.asarray(float(i)) for i, key in enumerate(rng.permutation(keys).tolist())}


def test_keys_come_back_in_the_order_they_went_in_with_unnamed_keys_untouched() -> None:
    arrays = _minimal()
    arrays = {"ns_codes": np.arange(3), **arrays, "nc_history": np.ones((2, 4), dtype=bool)}
    typed = EngineSnapshot.from_arrays(arrays)
    assert set(typed.extra) == {"ns_codes", "nc_history"}
    _assert_identical(typed.to_arrays(), arrays)
    assert typed.map.pc_lever is None and "em_pc_lever" not in typed.to_arrays()  # absent stays absent


def test_a_changed_or_added_field_is_written_under_its_key() -> None:
    arrays = _minimal()
    typed = EngineSnapshot.from_arrays(arrays)
    lever = np.zeros(4)
    moved = typed.replace(map=typed.map.replace(pose=np.ones((1, 4)), pc_lever=lever))
    out = moved.to_arrays()
    assert list(out)[: len(arrays)] == list(arrays) and list(out)[len(arrays) :] == ["em_pc_lever"]
    assert out["em_pc_lever"] is lever and np.array_equal(out["em_pose"], np.ones((1, 4)))
    assert typed.to_arrays()["em_pose"] is arrays["em_pose"]  # the original is not changed


def test_a_missing_required_key_is_named_and_optional_ones_are_not_required() -> None:
    arrays = _minimal()
    del arrays["em_link_kind"], arrays["gate_state"]
    with pytest.raises(MissingKeysError) as caught:
        EngineSnapshot.from_arrays(arrays)
    assert caught.value.keys == ["em_link_kind", "gate_state"]  # schema order
    assert "em_pc_lever" in EngineSnapshot.optional_keys() and "em_pc_lever" not in EngineSnapshot.required_keys()


def test_other_pose_cell_models_have_no_pose_cell_part() -> None:
    arrays = {k: v for k, v in _minimal().items() if not k.startswith("pc_")}
    arrays["ml_best"] = np.zeros(3)
    typed = EngineSnapshot.from_arrays(arrays)
    assert typed.pose_cells is None and set(typed.extra) == {"ml_best"}
    _assert_identical(typed.to_arrays(), arrays)


def test_a_part_spells_its_keys_from_its_prefix_and_field_names() -> None:
    assert ExperienceMapSnapshot.key("link_from") == "em_link_from"
    assert ExperienceMapSnapshot.key("pc_lever") == "em_pc_lever"
    assert PoseCellSnapshot.all_keys()[0] == "pc_activity"
    with pytest.raises(KeyError):
        ExperienceMapSnapshot.key("nonsense")
    assert len(set(EngineSnapshot.all_keys())) == len(EngineSnapshot.all_keys())  # no key named twice

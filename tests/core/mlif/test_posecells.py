"""PC-MLIF behind the engine: selection by ``pc_model``, the key's validation, snapshot/restore bit for bit."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

from core import Engine
from core.config import ConfigError, Params
from core.engine import pose_cells_class
from core.mlif import MlifPoseCells
from core.motion import Motion
from core.posecells import PoseCellNetwork
from tests.worlds import StripWorld


def _params(**changes: object) -> Params:
    base: dict[str, object] = {
        "template_x_size": 32, "template_y_size": 12, "vt_shift_match": 2, "vt_step_match": 1,
        "vt_match_threshold": 0.03, "pc_dim_xy": 21, "pc_dim_th": 36, "pc_cell_x_size": 1.0,
        "exp_delta_pc_threshold": 2.0, "exp_loops": 20, "vt_min_inject_age": 5, "exp_initial_em_deg": 0.0,
        "pc_model": "mlif",
    }
    base.update(changes)
    return Params().replace(**base)


def _same_state(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert a[key].dtype == b[key].dtype, key
        assert np.array_equal(a[key], b[key], equal_nan=True), key


def test_pc_model_selects_the_pose_cells() -> None:
    assert Params().pc_model == "can"
    assert pose_cells_class(Params()) is PoseCellNetwork
    assert pose_cells_class(Params(pc_model="mlif")) is MlifPoseCells
    assert isinstance(Engine(Params(pc_model="mlif")).pose_cells, MlifPoseCells)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"pc_model": "snn"}, "parameter 'pc_model' = 'snn': must be one of can, mlif"),
        ({"pc_model": "mlif", "engine": "neuroslam"}, "mlif pose cells belong to the ratslam engine"),
    ],
)
def test_a_bad_pc_model_is_refused(changes: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        Params().replace(**changes)


def test_the_codes_have_the_cans_rank() -> None:
    assert MlifPoseCells(_params()).rank == 3 == len(MlifPoseCells(_params()).best)
    four = MlifPoseCells(_params(pc_dim_z=5, pc_dim_xy=9, pc_dim_th=8))
    assert four.rank == 4 and four.position.shape == (9, 9, 5) and four.heading.shape == (9, 9, 8)


def test_the_engine_maps_with_mlif_and_restores_bit_for_bit(strip_world: StripWorld) -> None:
    """Processing 1..N equals 1..k, snapshot through a file, restore, k+1..N — every array, every bit."""
    frames = list(strip_world.drive(laps=1.6, yaw_bias=0.02))
    whole = Engine(_params())
    for image, motion, stamp in frames:
        whole.step(image, motion, stamp)
    assert whole.loop_closures >= 1  # the second lap is recognised through the spiking pose cells
    first = Engine(_params())
    for image, motion, stamp in frames[:60]:
        first.step(image, motion, stamp)
    buffer = io.BytesIO()
    np.savez(buffer, **first.snapshot())
    buffer.seek(0)
    with np.load(buffer) as data:
        state = {key: data[key] for key in data.files}
    assert "ml_head_v" in state and "pc_activity" not in state
    resumed = Engine.restore(_params(), state)
    for image, motion, stamp in frames[60:]:
        resumed.step(image, motion, stamp)
    _same_state(whole.snapshot(), resumed.snapshot())


def test_4dof_state_restores_bit_for_bit() -> None:
    params = _params(pc_dim_xy=9, pc_dim_z=5, pc_dim_th=8, pc_cell_x_size=0.5, pc_cell_z_size=0.5)
    world = StripWorld(perimeter_m=30.0, seed=5)
    frames = [(image, Motion(motion.dx, motion.dy, 0.02 * math.sin(i / 5), motion.dyaw, motion.dt), stamp)
              for i, (image, motion, stamp) in enumerate(world.drive(laps=1.2, yaw_bias=0.03))]
    whole = Engine(params)
    for frame in frames:
        whole.step(*frame)
    first = Engine(params)
    for frame in frames[:30]:
        first.step(*frame)
    resumed = Engine.restore(params, first.snapshot())
    for frame in frames[30:]:
        resumed.step(*frame)
    _same_state(whole.snapshot(), resumed.snapshot())

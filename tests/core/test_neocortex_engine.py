"""The sdr-htm front-end in the engine: recognition on revisits, exact resume, backbones and their weight files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from core.config import ConfigError, load_config, preset
from core.engine import Engine
from core.neocortex import NeocortexViewCells, WeightsError
from core.neocortex.backbones import AlexNet, ShuffleNetV2, build_backbone, preprocess
from core.neocortex.encoder import Encoder, resolve_device
from tests.worlds import StripWorld

SDR = preset("irat").replace(frontend="sdr-htm")  # small lattice, 60 × 20 templates for the weight-free encoder


def _run(engine: Engine, frames: list) -> list[tuple[int, bool]]:  # type: ignore[type-arg]
    return [(r.template, r.template_created) for r in (engine.step(*f) for f in frames)]


def test_revisits_recall_the_first_lap_cells_and_new_places_make_new_cells() -> None:
    """Laps 2 and 3 of an exactly repeating route match lap 1's cells of the same place; lap 1 creates."""
    world = StripWorld(seed=3)
    frames = list(world.drive(laps=3.0))
    per_lap = len(frames) // 3
    engine = Engine(SDR)
    rows = _run(engine, frames)
    lap1, lap2, lap3 = rows[:per_lap], rows[per_lap : 2 * per_lap], rows[2 * per_lap :]
    assert sum(created for _, created in lap1) >= 0.9 * per_lap  # must still happen: new places, new cells
    same_place = [a[0] == b[0] for a, b in zip(lap1, lap2, strict=True)]
    assert sum(same_place) >= 0.9 * per_lap
    assert sum(not created for _, created in lap3) >= 0.9 * per_lap
    assert engine.loop_closures > 0
    # a different world is not recognised: its first lap creates cells
    other = _run(engine, list(StripWorld(seed=11).drive(laps=0.5)))
    assert sum(created for _, created in other) >= 0.9 * len(other)


SMALL = SDR.replace(lsbh_bits=512, sp_columns=512, sp_potential_radius=150, sp_num_active_columns=12,
                    tm_cells_per_column=8, sv_tm_topk=10, sv_min_intersection=8, sp_boost_strength=1.0)


def test_split_run_equals_one_run_bit_for_bit() -> None:
    """Frames 1..N in one engine equal 1..k, snapshot, restore, k+1..N (boosting on, so duty cycles matter)."""
    frames = list(StripWorld(perimeter_m=30.0, seed=5).drive(laps=1.6))
    whole = Engine(SMALL)
    _run(whole, frames)
    first = Engine(SMALL)
    _run(first, frames[:55])
    resumed = Engine.restore(SMALL, first.snapshot())
    _run(resumed, frames[55:])
    a, b = whole.snapshot(), resumed.snapshot()
    assert list(a) == list(b)
    for key in a:
        assert a[key].dtype == b[key].dtype and a[key].shape == b[key].shape, key
        assert a[key].tobytes() == b[key].tobytes(), key
    assert a["lv_templates"].shape[1:] == (1, SMALL.sv_tm_topk) and "nc_projection" in a and "nc_tm_syn_perm" in a
    assert whole.template_count == int(a["lv_means"].shape[0]) > 10
    assert whole.loop_closures > 0  # the second lap was recognised


def test_each_view_cell_keeps_the_packed_sdr_of_the_frame_that_made_it() -> None:
    """``lv_sdr`` row i = packbits(SDR of the frame that created cell i), computed again by an independent cortex."""
    frames = list(StripWorld(perimeter_m=30.0, seed=5).drive(laps=0.6))
    engine = Engine(SMALL)
    made = [i for i, (_, created) in enumerate(_run(engine, frames)) if created]
    codes = engine.snapshot()["lv_sdr"]
    assert codes.shape == (len(made), SMALL.lsbh_bits // 8) and codes.dtype == np.uint8
    fresh = NeocortexViewCells(SMALL)  # the projection is fixed: a new cortex gives the same SDR
    for cell, frame in enumerate(made[:5]):
        expected = np.packbits(fresh.sdr(frames[frame][0]).numpy())
        np.testing.assert_array_equal(codes[cell], expected)
        assert int(np.unpackbits(codes[cell]).sum()) == 2 * int(SMALL.lsbh_s * SMALL.lsbh_bits / 2)  # 2k ones
    again = Engine.restore(SMALL, engine.snapshot())
    np.testing.assert_array_equal(again.snapshot()["lv_sdr"], codes)
    older = {k: v for k, v in engine.snapshot().items() if k != "lv_sdr"}  # stored before the key
    assert not Engine.restore(SMALL, older).snapshot()["lv_sdr"].any()


def test_added_prototypes_are_matched_kept_in_snapshots_and_padded_with_unknown_codes() -> None:
    """``add_prototypes`` prefills the store (the throughput bench's way): the matcher then finds those rows.

    Two rows of ``sv_tm_topk`` = 10 ids and one of 9 (padded −1). A descriptor sharing 9 ids with row 1 and 1 with
    row 0: I = 9, R = 9/10, F1 = 2·9/(10 + 10) = 0.9 ≥ 0.55, accepted (I_min 8); one sharing 5 with row 2 only:
    I = 5 < 8, refused.
    """
    cells = NeocortexViewCells(SMALL)
    rows = np.array([np.arange(0, 10), np.arange(100, 110), [*range(200, 209), -1]])
    codes = np.zeros((2, SMALL.lsbh_bits // 8), dtype=np.uint8)
    codes[0, 0], codes[1, -1] = 0b1000_0001, 0b0100_0000
    cells.add_prototypes(rows, np.array([10, 10, 9]), codes)  # codes for the first two rows only
    assert cells.count == 3
    stored, sizes = cells.prototypes
    np.testing.assert_array_equal(stored, rows)
    np.testing.assert_array_equal(sizes, [10, 10, 9])
    assert cells.codes[0, 0] == 0b1000_0001 and cells.codes[1, -1] == 0b0100_0000
    assert not cells.codes[2].any() and int(np.count_nonzero(cells.codes)) == 2  # the third row: unknown (zeros)
    found = cells.match(np.array([0, *range(101, 110)]))
    assert found is not None and found.accepted
    assert (found.index, found.intersection, found.recall, found.f1) == (1, 9, 0.9, 0.9)
    weak = cells.match(np.array([200, 201, 202, 203, 204, 900, 901, 902, 903, 904]))
    assert weak is not None and (weak.index, weak.intersection, weak.accepted) == (2, 5, False)
    again = NeocortexViewCells.restore(SMALL, cells.snapshot())
    np.testing.assert_array_equal(again.prototypes[0], rows)
    np.testing.assert_array_equal(again.codes, cells.codes)


def test_restore_refuses_a_projection_of_another_seed() -> None:
    engine = Engine(SMALL)
    _run(engine, list(StripWorld().drive(laps=0.1)))
    state = engine.snapshot()
    Engine.restore(SMALL, state)  # must still work unchanged
    state["nc_projection"] = state["nc_projection"] * np.float32(2.0)
    with pytest.raises(ValueError, match="projection"):
        Engine.restore(SMALL, state)


def test_lvc_presets_keep_lvc_and_the_sdr_presets_select_it() -> None:
    assert preset("poseidon-lvc").frontend == "lvc" and preset("irat").frontend == "lvc"
    assert preset("poseidon").frontend == "sdr-htm" and preset("neoslam").frontend == "sdr-htm"  # issue 17 item 4
    assert preset("poseidon-sdr") == preset("poseidon")  # an older name of the same preset
    assert isinstance(Engine(preset("poseidon")).local_view, NeocortexViewCells)
    sdr = preset("poseidon")
    assert (sdr.sp_columns, sdr.sp_num_active_columns, sdr.sp_potential_radius, sdr.tm_cells_per_column) == (
        2048, 20, 600, 40)
    assert (sdr.sv_tm_window, sdr.sv_tm_topk, sdr.sv_tm_match_threshold) == (7, 15, 0.3)
    # the weight-free encoder's input and gate are ours (core/config/_presets.py); NeoSLAM keeps the thesis's I_min 12
    assert (sdr.template_x_size, sdr.template_y_size, sdr.sv_min_intersection) == (16, 6, 8)
    assert preset("neoslam").sv_min_intersection == 12
    with pytest.raises(ConfigError, match="frontend"):
        preset("poseidon-lvc").replace(frontend="cnn")


NEOSLAM_YAML = """\
ratslam_pose_cells:
  ros__parameters:
    pose_cell:
      pc_dim_xy: 30
      pc_dim_th: 36
      pc_w_e_dim: 7
      pc_w_i_dim: 5
      pc_w_e_var: 1
      pc_w_i_var: 2
      pc_global_inhib: 0.00002
      vt_active_decay: 1.0
      pc_vt_inject_energy: 0.15
      pc_cell_x_size: 1.0
      exp_delta_pc_threshold: 2.0
      pc_vt_restore: 0.05
    draw:
      enable: true
      vt_window_width: 416
      vt_window_height: 480

ratslam_experience_map:
  ros__parameters:
    experience_map:
      exp_correction: 0.5
      exp_loops: 1
      exp_initial_em_deg: 90.0
      max_goals: 10
    draw:
      enable: true
      vt_window_width: 416
      vt_window_height: 480
"""


def test_the_neoslam_robotarium_yaml_loads_as_it_is(tmp_path: Path) -> None:
    """fjscoelho/ratslam config/neoslam_robotarium.yaml (key names and values as in that file)."""
    path = tmp_path / "neoslam_robotarium.yaml"
    path.write_text(NEOSLAM_YAML, encoding="utf-8")
    loaded = load_config(path)
    assert (loaded.pc_dim_xy, loaded.pc_dim_th, loaded.exp_loops, loaded.pc_vt_inject_energy) == (30, 36, 1, 0.15)
    assert load_config(path, base=preset("neoslam")) == preset("neoslam")  # the preset is that file
    assert load_config(path, base=preset("circle")) != preset("neoslam")  # must still differ from another base


def test_torchvision_key_names_and_parameter_counts() -> None:
    """The modules' state-dict keys are torchvision's; parameter counts are the published 2,278,604 / 61,100,840."""
    shuffle, alex = ShuffleNetV2().state_dict(), AlexNet().state_dict()
    for key in ("conv1.0.weight", "conv1.1.running_var", "stage2.0.branch1.0.weight", "stage2.0.branch2.6.bias",
                "stage3.7.branch2.5.weight", "stage4.3.branch2.0.weight", "conv5.1.num_batches_tracked", "fc.bias"):
        assert key in shuffle, key
    assert "stage2.1.branch1.0.weight" not in shuffle  # stride-1 units have an empty branch1
    for key in ("features.0.weight", "features.6.weight", "features.10.bias", "classifier.1.weight",
                "classifier.6.bias"):
        assert key in alex, key
    assert sum(p.numel() for p in ShuffleNetV2().parameters()) == 2_278_604
    assert sum(p.numel() for p in AlexNet().parameters()) == 61_100_840


def test_a_weight_file_loads_and_gives_the_source_models_features(tmp_path: Path) -> None:
    torch.manual_seed(0)
    source = ShuffleNetV2().eval()
    for module in source.modules():  # non-trivial batch-norm statistics
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_mean.uniform_(-0.1, 0.1)
            module.running_var.uniform_(0.5, 1.5)
    path = tmp_path / "shufflenet.pth"
    torch.save(source.state_dict(), path)
    loaded = build_backbone("shufflenetv2", path, torch.device("cpu"))
    image = (np.arange(96 * 256 * 3) % 251).astype(np.uint8).reshape(96, 256, 3)
    x = preprocess(image, torch.device("cpu"))
    assert x.shape == (1, 3, 224, 224)
    with torch.no_grad():
        assert torch.equal(loaded.embed(x), source.embed(x))
        assert loaded.embed(x).shape == (1, 232 * 14 * 14)
    wrapped = tmp_path / "wrapped.pth"
    torch.save({"state_dict": source.state_dict()}, wrapped)
    params = preset("poseidon-sdr").replace(frontend_backbone="shufflenetv2", frontend_weights=str(wrapped),
                                            lsbh_bits=256)
    cells = NeocortexViewCells(params)
    assert cells.encoder.dims == 45_472 and "nc_projection" not in cells.snapshot()  # too big: kept by digest
    cells.process(image)
    assert cells.count == 1


def test_bad_weight_files_are_refused_with_one_line(tmp_path: Path) -> None:
    with pytest.raises(WeightsError, match="needs a weights file"):
        build_backbone("alexnet", "", torch.device("cpu"))
    with pytest.raises(WeightsError, match="cannot read"):
        build_backbone("alexnet", tmp_path / "missing.pth", torch.device("cpu"))
    wrong = tmp_path / "wrong.pth"
    torch.save({"features.0.weight": torch.zeros(3)}, wrong)
    with pytest.raises(WeightsError, match="do not fit alexnet"):
        build_backbone("alexnet", wrong, torch.device("cpu"))


def test_weight_free_encoder_is_the_centred_local_view_template() -> None:
    image = StripWorld().view(3.0)
    y = Encoder(SDR, torch.device("cpu"))(image)
    assert y.shape == (1, SDR.template_x_size * SDR.template_y_size)
    assert abs(float(y.sum())) < 1e-3


def test_device_choice() -> None:
    assert resolve_device("cpu").type == "cpu"
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA"):
            resolve_device("cuda")


def test_the_sp_descriptor_source_uses_columns_and_the_tm_source_cells() -> None:
    """Ablation switch: ``sp`` describes a view by SP columns (ids < sp_columns), ``tm`` by TM cells."""
    images = [StripWorld().view(0.5 * i) for i in range(6)]
    sp_cells = NeocortexViewCells(SMALL.replace(sv_descriptor_source="sp"))
    tm_cells = NeocortexViewCells(SMALL)
    for image in images:
        sp_cells.process(image)
        tm_cells.process(image)
    pooled = set(np.concatenate(sp_cells.history).tolist())
    assert set(sp_cells.last_view.tolist()) <= pooled and max(pooled) < SMALL.sp_columns
    assert all(h.size <= SMALL.sp_num_active_columns for h in sp_cells.history)  # one id per active column
    assert int(tm_cells.last_view.max()) >= SMALL.sp_columns  # cell ids: column·cells + i
    assert set((tm_cells.last_view // SMALL.tm_cells_per_column).tolist()) <= set(range(SMALL.sp_columns))

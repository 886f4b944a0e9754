"""Presets and config files: OpenRatSLAM INI, OpenRatSLAM2 ROS 2 YAML, unknown-key errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from core.config import PRESETS, ConfigError, Params, load_config, params_from_dict, preset

# OpenRatSLAM config_irataus layout: [general], [ratslam] with spaced and unspaced '=', a whitespace-only
# line, and a [draw] section of viewer keys the engine does not use.
IRAT_INI = """[general]
topic_root=irat_red
\t
[ratslam]
image_crop_y_max=150
template_x_size=60
template_y_size=20
vt_shift_match = 4
vt_step_match = 1
vt_match_threshold = 0.03
vt_active_decay = 1.0

pc_dim_xy = 11
pc_vt_inject_energy = 0.1
pc_cell_x_size = 0.015

exp_delta_pc_threshold = 2
exp_loops=20
exp_initial_em_deg=140

[draw]
enable=1
vt_window_width=416
vt_window_height=480
exp_map_size=500
posecells_size=250
media_path=../src/media
image_file=irat_sm.tga
"""

# OpenRatSLAM2 (ROS 2) layout: one node per block, parameters under ros__parameters.
STLUCIA_YAML = """ratslam_view_template:
  ros__parameters:
    image_crop_x_min: 40
    image_crop_x_max: 600
    image_crop_y_min: 150
    image_crop_y_max: 300
    template_x_size: 60
    template_y_size: 10
    vt_shift_match: 5
    vt_step_match: 1
    vt_match_threshold: 0.085
    vt_normalisation: 0.4
    # draw
    enable: true
    vt_window_width: 640

ratslam_pose_cells:
  ros__parameters:
    pc_dim_xy: 30
    pc_vt_inject_energy: 0.15
    pc_cell_x_size: 2.0
    exp_delta_pc_threshold: 1.0
    pc_vt_restore: 0.04

ratslam_experience_map:
  ros__parameters:
    exp_loops: 20

ratslam_visual_odometry:
  ros__parameters:
    vtrans_image_x_min: 195
    vtrans_image_x_max: 475
    vtrans_image_y_min: 270
    vtrans_image_y_max: 430
    vrot_image_x_min: 195
    vrot_image_x_max: 475
    vrot_image_y_min: 75
    vrot_image_y_max: 240
    camera_fov_deg: 53.0
    vtrans_scaling: 1000.0
"""


def test_every_preset_of_the_issue_exists_and_is_valid() -> None:
    for name in ("irat", "stlucia", "newcollege", "lake", "circle", "poseidon"):
        assert isinstance(preset(name), Params)
    assert set(PRESETS) >= {"default", "irat", "stlucia", "newcollege", "lake", "circle", "poseidon"}


def test_preset_values_follow_their_sources() -> None:
    irat = preset("irat")  # OpenRatSLAM config_irataus
    assert (irat.template_x_size, irat.template_y_size, irat.image_crop_y_max) == (60, 20, 150)
    assert (irat.vt_shift_match, irat.vt_step_match, irat.vt_match_threshold) == (4, 1, 0.03)
    assert (irat.pc_dim_xy, irat.pc_dim_th, irat.pc_cell_x_size, irat.pc_vt_inject_energy) == (11, 36, 0.015, 0.1)
    assert (irat.exp_loops, irat.exp_initial_em_deg, irat.lattice_shape) == (20, 140.0, (11, 11, 36))
    newcollege = preset("newcollege")  # panoramic, patch-normalised
    assert newcollege.vt_panoramic and newcollege.vt_patch_normalise == 2 and newcollege.exp_loops == 100
    poseidon = preset("poseidon")  # thesis Table 4.1
    assert poseidon.lattice_shape == (15, 15, 15, 8) and poseidon.lattice_rank == 4
    assert (poseidon.pc_cell_x_size, poseidon.pc_cell_z_size) == (0.1, 0.1)
    assert (poseidon.vpr_guard, poseidon.vpr_window, poseidon.vpr_leak_rate) == (True, 26, 20)
    assert poseidon.vpr_min_rep == 2 and preset("poseidon-lvc").vpr_min_rep == 3  # ours for the weight-free encoder
    assert (poseidon.motion_gate, poseidon.min_event_trans_xy, poseidon.min_event_dz) == (True, 0.12, 0.05)
    assert (poseidon.max_correction_norm, poseidon.max_correction_step) == (20.0, 0.05)
    lvc = preset("poseidon-lvc")  # the same back-end with intensity templates
    assert lvc.lattice_shape == poseidon.lattice_shape and lvc.motion_gate and lvc.vpr_guard
    assert (lvc.template_x_size, lvc.template_y_size, lvc.vt_match_threshold) == (64, 24, 0.06)
    for name in ("irat", "stlucia", "newcollege", "lake", "circle"):  # PoseidonSLAM options are off in RatSLAM sets
        assert not preset(name).vpr_guard and not preset(name).motion_gate


def test_unknown_preset_names_the_closest() -> None:
    with pytest.raises(ConfigError, match=r"unknown preset 'irta'.*did you mean 'irat'"):
        preset("irta")


def test_openratslam_ini_loads_as_it_is(tmp_path: Path) -> None:
    path = tmp_path / "config_irataus.txt"
    path.write_text(IRAT_INI, encoding="utf-8")
    loaded = load_config(path)
    assert loaded == preset("irat")


def test_openratslam2_yaml_loads_as_it_is(tmp_path: Path) -> None:
    path = tmp_path / "config_stlucia.yaml"
    path.write_text(STLUCIA_YAML, encoding="utf-8")
    loaded = load_config(path)
    stlucia = preset("stlucia")
    assert loaded == stlucia.replace(camera_hz=loaded.camera_hz)  # the YAML leaves camera_hz at its default
    assert loaded.vrot_image_y_max == 240 and loaded.vtrans_scaling == 1000.0


def test_yaml_without_a_yaml_suffix_is_detected(tmp_path: Path) -> None:
    path = tmp_path / "ratslam_params.txt"
    path.write_text(STLUCIA_YAML, encoding="utf-8")
    assert load_config(path).pc_dim_xy == 30


@pytest.mark.parametrize(
    ("suffix", "text"),
    [
        (".txt", "[ratslam]\npc_dim_xy = 11\nvt_match_treshold = 0.03\n"),
        (".yaml", "ratslam_view_template:\n  ros__parameters:\n    vt_match_treshold: 0.03\n"),
    ],
)
def test_unknown_key_is_an_error_naming_the_key_and_the_closest(tmp_path: Path, suffix: str, text: str) -> None:
    path = tmp_path / f"config{suffix}"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert "'vt_match_treshold'" in message and "did you mean 'vt_match_threshold'" in message
    assert str(path) in message and "\n" not in message


def test_invalid_values_and_aliases() -> None:
    with pytest.raises(ConfigError, match="pc_dim_xy"):
        params_from_dict({"pc_dim_xy": "eleven"})
    with pytest.raises(ConfigError, match="exp_correction"):
        params_from_dict({"exp_correction": 0})
    with pytest.raises(ConfigError, match="odd"):
        params_from_dict({"pc_w_e_dim": 6})
    assert params_from_dict({"vt_normalization": "0.4"}).vt_normalisation == 0.4  # US spelling in some files
    assert params_from_dict({"vt_panoramic": "1"}).vt_panoramic is True
    with pytest.raises(ConfigError, match=r"did you mean 'exp_loops'"):
        Params().replace(exp_loop=3)
    with pytest.raises(ConfigError, match=r"merge_probation_max_m.*or -1"):
        params_from_dict({"merge_probation_max_m": -2})
    assert params_from_dict({"merge_probation_max_m": "200"}).merge_probation_max_m == 200.0


@pytest.mark.parametrize("value", ["nan", "NaN", "inf", "-inf", "1e400"])
def test_non_finite_values_are_refused_for_every_float_key(value: str) -> None:
    """NaN passes every range check (each comparison is false), ±inf passes one-sided ones: both are refused."""
    for key in ("vt_match_threshold", "exp_delta_pc_threshold", "merge_evidence_m", "camera_fov_deg", "min_f1"):
        with pytest.raises(ConfigError, match=rf"parameter '{key}' = .*: must be a finite number"):
            params_from_dict({key: value})
    assert params_from_dict({"vt_match_threshold": "1e300"}).vt_match_threshold == 1e300  # finite: kept


def test_missing_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(tmp_path / "absent.txt")
    bad = tmp_path / "bad.yaml"
    bad.write_text("ratslam: [unclosed\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="malformed YAML"):
        load_config(bad)


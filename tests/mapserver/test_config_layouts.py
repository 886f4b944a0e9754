"""OpenRatSLAM2 (fjscoelho/ratslam ``config/``) parameter files load as they are.

The layouts below are those of that repository's files — sections, node names, nested parameter groups,
CRLF line endings, the whitespace-and-tab line after ``[general]``, commented-out keys, viewer and ROS keys,
``@MEDIA_PATH@`` placeholders — written here key by key (key names and structure are data; no file is
copied). Each must load through ``--config`` with the values it states.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from core.config import ConfigError
from mapserver.params import resolve_params

BLANK_WITH_TAB = " " * 48 + "\t"

IRATAUS_TXT = (
    "[general]\ntopic_root=irat_red\n" + BLANK_WITH_TAB + "\n[ratslam]\nimage_crop_y_max=150\ntemplate_x_size=60\n"
    "template_y_size=20\nvt_shift_match = 4\nvt_step_match = 1\nvt_match_threshold = 0.03\nvt_active_decay = 1.0\n\n"
    "pc_dim_xy = 11\npc_vt_inject_energy = 0.1\npc_cell_x_size = 0.015\n\nexp_delta_pc_threshold = 2\nexp_loops=20\n"
    "exp_initial_em_deg=140\n\n[draw]\nenable=1\nvt_window_width=416\nvt_window_height=480\nexp_map_size=500\n"
    "posecells_size=250\n"
).replace("\n", "\r\n")

IRATAUS_YAML = (
    "ratslam_view_template:\n  ros__parameters:\n    image_crop_y_max: 150\n    template_x_size: 60\n"
    "    template_y_size: 20\n    vt_shift_match: 4\n    vt_step_match: 1\n    vt_match_threshold: 0.03\n"
    "    # draw\n    enable: true\n    vt_window_width: 416\n    vt_window_height: 480\n\n"
    "ratslam_pose_cells:\n  ros__parameters:\n    pc_dim_xy: 11\n    pc_vt_inject_energy: 0.1\n"
    "    pc_cell_x_size: 0.015\n    exp_delta_pc_threshold: 2.0\n    # draw\n    enable: true\n\n"
    "ratslam_experience_map:\n  ros__parameters:\n    exp_loops: 20\n    exp_initial_em_deg: 140.0\n"
    "    # draw\n    enable: true\n"
).replace("\n", "\r\n")

STLUCIA_TXT = (
    "[general]\ntopic_root=stlucia\n" + BLANK_WITH_TAB + "\n[ratslam]\nimage_crop_x_min=40\nimage_crop_x_max=600\n"
    "image_crop_y_min=150\nimage_crop_y_max=300\nvt_match_threshold = 0.085\ntemplate_x_size=60\ntemplate_y_size=10\n"
    "vt_shift_match = 5\nvt_step_match = 1\nvt_normalisation = 0.4\npc_vt_restore=0.04\n\npc_cell_x_size = 2\n"
    "pc_dim_xy = 30\nexp_delta_pc_threshold = 1.0\npc_vt_inject_energy = 0.15\nvt_active_decay = 1.0\n\n"
    "exp_loops=20\n\n\n"
    "[visual_odometry]\nvtrans_image_x_min=195\nvtrans_image_x_max=475\nvtrans_image_y_min=270\nvtrans_image_y_max=430\n\n"
    "vrot_image_x_min=195\nvrot_image_x_max=475\nvrot_image_y_min=75\nvrot_image_y_max=240\n\ncamera_fov_deg=53\n"
    "camera_hz = 10\nvtrans_scaling = 1000\nvtrans_max=20\n\n[draw]\nenable=1\nvt_window_width=640\n"
    "vt_window_height=900\nexp_map_size=500\nposecells_size=250\nmedia_path=@MEDIA_PATH@\nimage_file=irat_sm.tga\n"
).replace("\n", "\r\n")

MMC_LAKE_VO_YAML = (
    "ratslam_view_template:\n  ros__parameters:\n    image_crop_x_min: 40\n    image_crop_x_max: 600\n"
    "    # image_crop_y_min: 150\n    image_crop_y_max: 350\n    template_x_size: 60\n    template_y_size: 24\n"
    "    vt_match_threshold: 0.0555\n    vt_panoramic: 0\n    vt_patch_normalise: 2\n    vt_shift_match: 5\n"
    "    vt_step_match: 1\n    vt_normalisation: 0.4\n    pc_vt_restore: 0.04\n    # draw\n    enable: true\n"
    "    vt_window_width: 416\n    vt_window_height: 480\nratslam_pose_cells:\n  ros__parameters:\n"
    "    pc_cell_x_size: 1.0\n    pc_dim_xy: 18\n    exp_delta_pc_threshold: 1.0\n    pc_vt_inject_energy: 0.2\n"
    "    vt_active_decay: 1.0\n    # draw\n    enable: true\n    posecells_size: 250\nratslam_experience_map:\n"
    "  ros__parameters:\n    exp_loops: 50\n    exp_initial_em_deg: 180.0\n    # draw\n    enable: true\n"
    "    exp_map_size: 500\nratslam_visual_odometry:\n  ros__parameters:\n    vtrans_image_x_min: 195\n"
    "    vtrans_image_x_max: 475\n    vtrans_image_y_min: 270\n    vtrans_image_y_max: 430\n    vrot_image_x_min: 195\n"
    "    vrot_image_x_max: 475\n    vrot_image_y_min: 75\n    vrot_image_y_max: 240\n    camera_fov_deg: 160.0\n"
    "    camera_hz: 1.0\n    vtrans_scaling: 100.0\n    vtrans_max: 1.0\n"
)

# config_robotarium.yaml / neoslam_robotarium.yaml: ROS 2 nested parameter groups under ros__parameters
_NESTED_POSE_CELLS = (
    "ratslam_pose_cells:\n  ros__parameters:\n    pose_cell:\n      pc_dim_xy: 30\n      pc_dim_th: 36\n"
    "      pc_w_e_dim: 7\n      pc_w_i_dim: 5\n      pc_w_e_var: 1\n      pc_w_i_var: 2\n"
    "      pc_global_inhib: 0.00002\n"
    "      vt_active_decay: 1.0\n      pc_vt_inject_energy: 0.15\n      pc_cell_x_size: 1.0\n"
    "      exp_delta_pc_threshold: 2.0\n      pc_vt_restore: 0.05\n    draw:\n      enable: true\n"
    "      vt_window_width: 416\n      vt_window_height: 480\n\nratslam_experience_map:\n  ros__parameters:\n"
    "    experience_map:\n      exp_correction: 0.5\n      exp_loops: 1\n      exp_initial_em_deg: 90.0\n"
    "      max_goals: 10\n    draw:\n      enable: true\n      vt_window_width: 416\n      vt_window_height: 480\n"
)
ROBOTARIUM_YAML = (
    "ratslam_view_template:\n  ros__parameters:\n    image_crop_y_max: 150\n    template_x_size: 60\n"
    "    template_y_size: 20\n    vt_shift_match: 4\n    vt_step_match: 1\n    vt_match_threshold: 0.03\n    # draw\n"
    "    enable: true\n    vt_window_width: 416\n    vt_window_height: 480\n\n" + _NESTED_POSE_CELLS
).replace("\n", "\r\n")
NEOSLAM_ROBOTARIUM_YAML = _NESTED_POSE_CELLS
NEOSLAM_ROBOTARIUM_TXT = (
    "[ratslam]\npc_dim_xy = 30\npc_dim_th = 36\npc_w_e_dim = 7\npc_w_i_dim = 5\npc_w_e_var = 1\npc_w_i_var = 2\n"
    "vt_active_decay = 1.0\npc_global_inhib = 0.00002\npc_vt_inject_energy = 0.15\npc_cell_x_size = 1.0\n"
    "exp_delta_pc_threshold = 2\nexp_loops=1\nexp_initial_em_deg=90.0\n\n[draw]\nenable=1\nvt_window_width=416\n"
    "vt_window_height=480\nexp_map_size=500\nposecells_size=250\n"
).replace("\n", "\r\n")

_ROBOTARIUM_CELLS = {"pc_dim_xy": 30, "pc_dim_th": 36, "pc_w_e_dim": 7, "pc_w_i_dim": 5, "pc_w_e_var": 1,
                     "pc_w_i_var": 2, "pc_global_inhib": 0.00002, "pc_vt_inject_energy": 0.15, "pc_cell_x_size": 1.0,
                     "exp_delta_pc_threshold": 2.0, "exp_loops": 1, "exp_initial_em_deg": 90.0}  # fmt: skip
CASES: dict[str, tuple[str, dict[str, Any]]] = {
    "config_irataus.txt.in": (IRATAUS_TXT, {"template_x_size": 60, "template_y_size": 20, "vt_match_threshold": 0.03,
                                            "pc_dim_xy": 11, "pc_cell_x_size": 0.015, "exp_loops": 20,
                                            "exp_initial_em_deg": 140.0, "image_crop_y_max": 150}),
    "config_irataus.yaml": (IRATAUS_YAML, {"template_x_size": 60, "template_y_size": 20, "pc_dim_xy": 11,
                                           "pc_vt_inject_energy": 0.1, "exp_loops": 20, "exp_initial_em_deg": 140.0}),
    "config_stlucia.txt.in": (STLUCIA_TXT, {"image_crop_x_min": 40, "vt_normalisation": 0.4, "pc_vt_restore": 0.04,
                                            "pc_cell_x_size": 2.0, "camera_fov_deg": 53.0, "camera_hz": 10.0,
                                            "vtrans_scaling": 1000.0, "vtrans_max": 20.0, "vrot_image_y_min": 75}),
    "config_surveyor_MMC_lake_VO.yaml": (MMC_LAKE_VO_YAML, {"image_crop_y_max": 350, "template_y_size": 24,
                                                            "vt_match_threshold": 0.0555, "vt_panoramic": False,
                                                            "vt_patch_normalise": 2, "pc_dim_xy": 18,
                                                            "exp_initial_em_deg": 180.0, "camera_fov_deg": 160.0,
                                                            "vtrans_scaling": 100.0}),
    "config_robotarium.yaml": (ROBOTARIUM_YAML, {"template_x_size": 60, "vt_match_threshold": 0.03,
                                                 "exp_correction": 0.5, **_ROBOTARIUM_CELLS}),
    "neoslam_robotarium.yaml": (NEOSLAM_ROBOTARIUM_YAML, _ROBOTARIUM_CELLS),
    "config_neoslam_robotarium.txt.in": (NEOSLAM_ROBOTARIUM_TXT, _ROBOTARIUM_CELLS),
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(CASES))
def test_openratslam2_config_layouts_load_as_they_are(tmp_path: Path, name: str) -> None:
    text, expected = CASES[name]
    path = tmp_path / name
    path.write_bytes(text.encode("utf-8"))
    params = resolve_params(None, path, None).to_dict()
    assert {key: params[key] for key in expected} == expected


def test_the_nested_groups_are_what_is_read(tmp_path: Path) -> None:
    # must still fail: a key inside a nested group that is no parameter is named, not silently dropped
    path = tmp_path / "neoslam_robotarium.yaml"
    path.write_text(NEOSLAM_ROBOTARIUM_YAML.replace("      pc_dim_th: 36\n", "      pc_dim_thh: 36\n"))
    with pytest.raises(ConfigError, match=r"unknown parameter 'pc_dim_thh' in .*neoslam_robotarium\.yaml.*'pc_dim_th'"):
        resolve_params(None, path, None)


def test_every_unsupported_key_is_named(tmp_path: Path) -> None:
    # keys of a front-end this engine does not have (here invented ones) are all named in one line
    path = tmp_path / "other_frontend.yaml"
    path.write_text(
        NEOSLAM_ROBOTARIUM_YAML
        + "other_front_end:\n  ros__parameters:\n    grid_cell_modules: 4\n    hd_cell_count: 36\n"
        + "    place_code_width: 0.3\n"
    )
    with pytest.raises(ConfigError) as info:
        resolve_params(None, path, None)
    message = str(info.value)
    assert "3 unknown parameters in" in message and "\n" not in message
    assert "'grid_cell_modules', 'hd_cell_count', 'place_code_width'" in message

"""Where each key of an engine snapshot is stored (the table in :mod:`mapserver.store.state`)."""

from __future__ import annotations

TEMPLATE_KEYS = ("lv_templates", "lv_means", "lv_origin")
POSE_CELL_LINK_KEYS = ("pc_link_template", "pc_link_coords", "pc_link_strength", "pc_link_decay")
EXPERIENCE_KEYS = ("em_pose", "em_pc", "em_template", "em_stamp", "em_origin")
LINK_KEYS = ("em_link_from", "em_link_to", "em_link_transform", "em_link_dt", "em_link_distance", "em_link_kind")
ACTIVITY_KEY = "pc_activity"
PLACES: dict[str, str] = {
    **dict.fromkeys(TEMPLATE_KEYS, "templates"),
    **dict.fromkeys(POSE_CELL_LINK_KEYS, "pose_cell_links"),
    **dict.fromkeys(EXPERIENCE_KEYS, "experiences"),
    **dict.fromkeys(LINK_KEYS, "links"),
    "em_link_active": "links",
    ACTIVITY_KEY: "pc_activity",
}
"""Snapshot key → where it is stored (keys not listed go to the ``arrays`` npz)."""
NEGZERO_PREFIX = "__negzero__."
"""Prefix of the npz entry that holds a row-table key's ``-0.0`` positions."""
ROW_FLOAT_KEYS = (
    "lv_means",
    "pc_link_coords",
    "pc_link_strength",
    "pc_link_decay",
    "em_pose",
    "em_pc",
    "em_stamp",
    "em_link_transform",
    "em_link_dt",
    "em_link_distance",
)
"""Row-table float columns: checked for NaN, and their ``-0.0`` signs kept as patches (SQLite drops them)."""

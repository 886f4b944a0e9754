"""Maps with a chosen experience graph, stored directly through the store API (no frames processed)."""

from __future__ import annotations

import numpy as np

from core import Engine, preset
from mapserver.store import NewSession, open_database, save_map


def store_graph_map(db_url: str, name: str, poses: np.ndarray, links: list[tuple[int, int, float, float]]) -> None:
    """Store map ``name`` whose experiences have ``poses`` (E, 4) and whose links are (from, to, dt, distance)."""
    params = preset("irat")
    snap = Engine(params).snapshot()
    e = poses.shape[0]
    ty, tx = params.template_y_size, params.template_x_size
    snap["lv_templates"] = np.full((1, ty, tx), 0.5, dtype=np.float32)
    snap["lv_means"] = np.array([0.5])
    snap["lv_origin"] = np.zeros(1, dtype=np.int64)
    snap["lv_current"] = np.asarray(0, dtype=np.int64)
    rank = snap["pc_activity"].ndim
    snap["em_pose"] = np.asarray(poses, dtype=np.float64)
    snap["em_pc"] = np.zeros((e, rank))
    snap["em_template"] = np.zeros(e, dtype=np.int64)
    snap["em_stamp"] = np.arange(e, dtype=np.float64)
    snap["em_origin"] = np.zeros(e, dtype=np.int64)
    arr = np.asarray(links, dtype=np.float64).reshape(-1, 4)
    snap["em_link_from"] = arr[:, 0].astype(np.int64)
    snap["em_link_to"] = arr[:, 1].astype(np.int64)
    snap["em_link_transform"] = np.zeros((arr.shape[0], 4))
    snap["em_link_dt"] = arr[:, 2].copy()
    snap["em_link_distance"] = arr[:, 3].copy()
    snap["em_link_kind"] = np.zeros(arr.shape[0], dtype=np.int8)
    snap["em_current"] = np.asarray(e - 1, dtype=np.int64)
    session = NewSession(name=name, log_name=f"{name}.bag", log_sha256=f"{abs(hash(name)):064x}"[-64:],
                         topics={"image": "/camera"}, params=params.to_dict(), frames_processed=e)  # fmt: skip
    with open_database(db_url) as db:
        save_map(db, name=name, params=params, snapshot=snap, sessions=[session])

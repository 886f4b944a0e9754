"""Writing a snapshot's row tables: experiences, links and pose-cell links rewritten, templates synced."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from sqlalchemy import Connection

from core.se3 import quaternions_from_yaws
from mapserver.store.bulk import bulk_insert
from mapserver.store.models import LINK_KIND_NAMES, Experience, Link, PoseCellLink
from mapserver.store.state_identities import SnapshotIdentities, check_experience_owners
from mapserver.store.state_params import frontend_of
from mapserver.store.state_templates import rewrite_reexpressed_templates, sync_templates
from mapserver.store.state_validate import Shapes


def replace_rows(
    conn: Connection, map_id: int, snapshot: Mapping[str, Any], shapes: Shapes, params: Any, rows: SnapshotIdentities
) -> None:
    """Rewrite the map's experience, link and pose-cell link rows and sync its template rows to the snapshot."""
    for table in (Link, PoseCellLink, Experience):
        conn.execute(table.__table__.delete().where(table.map_id == map_id))
    check_experience_owners(conn, map_id, rows.experience_sessions, rows.experience_index)
    templates, means = np.asarray(snapshot["lv_templates"]), np.asarray(snapshot["lv_means"])
    if frontend_of(params) == "sdr-htm":
        rewrite_reexpressed_templates(conn, templates, means, rows.template_sessions, rows.template_index)
    sync_templates(conn, map_id, templates, means, rows.template_sessions, rows.template_index)
    _insert_pose_cell_links(conn, map_id, snapshot, shapes.rank)
    _insert_experiences(conn, map_id, snapshot, shapes.rank, rows.experience_sessions, rows.experience_index)
    _insert_links(conn, map_id, snapshot)


def _coords(pc: np.ndarray, rank: int) -> tuple[list[float], list[float], list[float | None], list[float]]:
    """Split (R, D) lattice coordinates into the pc_x, pc_y, pc_z (None for D = 3), pc_th columns."""
    x = pc[:, 0].tolist()
    y = pc[:, 1].tolist()
    z: list[float | None] = pc[:, 2].tolist() if rank == 4 else [None] * pc.shape[0]
    th = pc[:, rank - 1].tolist()
    return x, y, z, th


def _insert_pose_cell_links(conn: Connection, map_id: int, snapshot: Mapping[str, Any], rank: int) -> None:
    """Insert the snapshot's LVC→pose-cell links (``pc_link_*``) in row order (``seq``)."""
    template = np.asarray(snapshot["pc_link_template"]).astype(np.int64).reshape(-1)
    coords = np.asarray(snapshot["pc_link_coords"], dtype=np.float64).reshape(-1, rank)
    x, y, z, th = _coords(coords, rank)
    count = template.shape[0]
    rows = list(
        zip(
            [map_id] * count,
            range(count),
            template.tolist(),
            x,
            y,
            z,
            th,
            np.asarray(snapshot["pc_link_strength"], dtype=np.float64).tolist(),
            np.asarray(snapshot["pc_link_decay"], dtype=np.float64).tolist(),
            strict=True,
        )
    )
    columns = ("map_id", "seq", "template", "pc_x", "pc_y", "pc_z", "pc_th", "strength", "decay")
    bulk_insert(conn, PoseCellLink.__table__, columns, rows)


def _insert_experiences(
    conn: Connection,
    map_id: int,
    snapshot: Mapping[str, Any],
    rank: int,
    sessions: np.ndarray,
    indices: np.ndarray,
) -> None:
    """Insert the snapshot's experiences (``em_*``) with their identities; yaw also as a quaternion."""
    pose = np.asarray(snapshot["em_pose"], dtype=np.float64).reshape(-1, 4)
    count = pose.shape[0]
    qx, qy, qz, qw = quaternions_from_yaws(pose[:, 3]).T.tolist()
    x, y, z, th = _coords(np.asarray(snapshot["em_pc"], dtype=np.float64).reshape(-1, rank), rank)
    rows = list(
        zip(
            [map_id] * count,
            range(count),
            sessions.tolist(),
            indices.tolist(),
            pose[:, 0].tolist(),
            pose[:, 1].tolist(),
            pose[:, 2].tolist(),
            qx,
            qy,
            qz,
            qw,
            pose[:, 3].tolist(),
            x,
            y,
            z,
            th,
            np.asarray(snapshot["em_template"]).astype(np.int64).tolist(),
            np.asarray(snapshot["em_stamp"], dtype=np.float64).tolist(),
            strict=True,
        )
    )
    columns = (
        "map_id", "local_id", "session_id", "origin_index", "x", "y", "z", "qx", "qy", "qz", "qw", "yaw",
        "pc_x", "pc_y", "pc_z", "pc_th", "template", "stamp",
    )  # fmt: skip
    bulk_insert(conn, Experience.__table__, columns, rows)


def _insert_links(conn: Connection, map_id: int, snapshot: Mapping[str, Any]) -> None:
    """Insert the snapshot's experience links (``em_link_*``) in row order (``seq``), kinds by name."""
    source = np.asarray(snapshot["em_link_from"]).astype(np.int64).reshape(-1)
    count = source.shape[0]
    transform = np.asarray(snapshot["em_link_transform"], dtype=np.float64).reshape(-1, 4)
    names = np.asarray(LINK_KIND_NAMES, dtype=object)[np.asarray(snapshot["em_link_kind"]).astype(np.int64)]
    active = np.asarray(snapshot.get("em_link_active", np.ones(count, dtype=bool)), dtype=bool).reshape(-1)
    rows = list(
        zip(
            [map_id] * count,
            range(count),
            source.tolist(),
            np.asarray(snapshot["em_link_to"]).astype(np.int64).tolist(),
            transform[:, 0].tolist(),
            transform[:, 1].tolist(),
            transform[:, 2].tolist(),
            transform[:, 3].tolist(),
            np.asarray(snapshot["em_link_dt"], dtype=np.float64).tolist(),
            np.asarray(snapshot["em_link_distance"], dtype=np.float64).tolist(),
            names.tolist(),
            active.tolist(),
            strict=True,
        )
    )
    columns = ("map_id", "seq", "from_id", "to_id", "dx", "dy", "dz", "dyaw", "dt", "distance", "kind", "active")
    bulk_insert(conn, Link.__table__, columns, rows)

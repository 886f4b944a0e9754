"""Reading a stored map's row tables back into snapshot arrays (templates, pose-cell links, experiences, links)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from sqlalchemy import Connection, case, select
from sqlalchemy.orm import InstrumentedAttribute

from mapserver.formats import LINK_KIND_CODES
from mapserver.store.bulk import fetch_tuples
from mapserver.store.errors import CorruptStateError
from mapserver.store.models import Experience, Link, PoseCellLink, Template


def _column_block(rows: Sequence[Any], columns: int) -> np.ndarray:
    """Return fetched rows as a (R, ``columns``) float64 block."""
    return np.array(rows, dtype=np.float64).reshape(-1, columns)


def read_map_templates(*, conn: Connection, map_id: int) -> np.ndarray:
    """Return a stored map's templates (N, ty, tx) float32 in id order, without the rest of its state."""
    rows = fetch_tuples(
        conn,
        select(Template.height, Template.width, Template.data).where(Template.map_id == map_id)
        .order_by(Template.local_id),
    )  # fmt: skip
    if not rows:
        return np.zeros((0, 0, 0), dtype=np.float32)
    h, w = int(rows[0][0]), int(rows[0][1])
    return np.frombuffer(b"".join(r[2] for r in rows), dtype="<f4").reshape(len(rows), h, w)


def read_templates(
    conn: Connection, name: str, map_id: int, manifest: dict[str, Any], built: dict[str, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Read the LVC templates into ``built`` (``lv_*``); return each template's session id and origin index."""
    rows = fetch_tuples(
        conn,
        select(
            Template.session_id, Template.origin_index, Template.local_id, Template.height, Template.width,
            Template.mean, Template.data,
        )
        .where(Template.map_id == map_id)
        .order_by(Template.local_id),
    )  # fmt: skip
    n = len(rows)
    head = np.array([r[:5] for r in rows], dtype=np.int64).reshape(-1, 5)
    if not np.array_equal(head[:, 2], np.arange(n)):
        msg = f"map {name!r}: template local ids are not 0..{n - 1}"
        raise CorruptStateError(msg)
    shape = manifest.get("lv_templates", {}).get("shape", [0, 0, 0])
    h, w = (int(head[0, 3]), int(head[0, 4])) if n else (int(shape[1]), int(shape[2]))
    blob = b"".join(r[6] for r in rows)
    built["lv_templates"] = np.frombuffer(blob, dtype="<f4").reshape(n, h, w)
    built["lv_means"] = np.array([r[5] for r in rows], dtype=np.float64)
    built["lv_origin"] = head[:, 0].copy()
    return head[:, 0].copy(), head[:, 1].copy()


def read_pose_cell_links(conn: Connection, map_id: int, rank: int, built: dict[str, np.ndarray]) -> None:
    """Read the LVC→pose-cell links into ``built`` (``pc_link_*``; coordinates of the lattice's ``rank``)."""
    pc_columns: list[InstrumentedAttribute[float | None]] = [
        PoseCellLink.template, PoseCellLink.pc_x, PoseCellLink.pc_y
    ]  # fmt: skip
    if rank == 4:
        pc_columns.append(PoseCellLink.pc_z)
    pc_columns += [PoseCellLink.pc_th, PoseCellLink.strength, PoseCellLink.decay]
    block = _column_block(
        fetch_tuples(conn, select(*pc_columns).where(PoseCellLink.map_id == map_id).order_by(PoseCellLink.seq)),
        len(pc_columns),
    )
    built["pc_link_template"] = block[:, 0].astype(np.int64)
    built["pc_link_coords"] = block[:, 1 : 1 + rank].copy()
    built["pc_link_strength"] = block[:, 1 + rank].copy()
    built["pc_link_decay"] = block[:, 2 + rank].copy()


def read_experiences(
    conn: Connection, map_id: int, rank: int, built: dict[str, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Read the experiences into ``built`` (``em_pose`` … ``em_origin``); return their sessions and origin indices."""
    em_columns: list[InstrumentedAttribute[float | None]] = [
        Experience.session_id, Experience.origin_index, Experience.x, Experience.y, Experience.z, Experience.yaw,
        Experience.pc_x, Experience.pc_y,
    ]  # fmt: skip
    if rank == 4:
        em_columns.append(Experience.pc_z)
    em_columns += [Experience.pc_th, Experience.template, Experience.stamp]
    block = _column_block(
        fetch_tuples(conn, select(*em_columns).where(Experience.map_id == map_id).order_by(Experience.local_id)),
        len(em_columns),
    )
    experience_session = block[:, 0].astype(np.int64)
    built["em_pose"] = block[:, 2:6].copy()
    built["em_pc"] = block[:, 6 : 6 + rank].copy()
    built["em_template"] = block[:, 6 + rank].astype(np.int64)
    built["em_stamp"] = block[:, 7 + rank].copy()
    built["em_origin"] = experience_session.copy()
    return experience_session, block[:, 1].astype(np.int64)


def read_links(conn: Connection, map_id: int, built: dict[str, np.ndarray]) -> None:
    """Read the experience links into ``built`` (``em_link_*``, kinds as their codes)."""
    kind_code = case(LINK_KIND_CODES, value=Link.kind, else_=-1)
    block = _column_block(
        fetch_tuples(
            conn,
            select(
                Link.from_id, Link.to_id, Link.dx, Link.dy, Link.dz, Link.dyaw, Link.dt, Link.distance, kind_code,
                Link.active,
            )
            .where(Link.map_id == map_id)
            .order_by(Link.seq),
        ),
        10,
    )
    built["em_link_from"] = block[:, 0].astype(np.int64)
    built["em_link_to"] = block[:, 1].astype(np.int64)
    built["em_link_transform"] = block[:, 2:6].copy()
    built["em_link_dt"] = block[:, 6].copy()
    built["em_link_distance"] = block[:, 7].copy()
    built["em_link_kind"] = block[:, 8].astype(np.int64)
    built["em_link_active"] = block[:, 9].astype(bool)

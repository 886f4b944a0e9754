"""Read a g2o file back as a stored map's experience poses (after optimising an exported graph elsewhere).

``mapserver import FILE.g2o --format g2o --map NAME`` replaces the pose of every experience of map NAME
with the pose of the vertex of the same id (the ids ``export --format g2o`` wrote). Everything else —
templates, links and their measurements, lattice state, sessions — stays as stored; the map's version
advances (one transaction, refused when another writer changed the map meanwhile). Links keep their
measured transforms, so a session that later continues the map relaxes it towards those again.

* The file must hold exactly one vertex per experience (ids 0 … E − 1), nothing more, nothing less.
* ``VERTEX_SE2`` gives x, y and yaw (z stays as stored); ``VERTEX_SE3:QUAT`` gives x, y, z and the
  rotation's yaw. RatSLAM maps hold no roll or pitch: an SE3 vertex tilted by more than
  :data:`MAX_TILT_RAD` is refused (the graph was optimised without the planar constraint).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mapserver.errors import InputError
from mapserver.formats.g2o import read_g2o_vertices
from mapserver.store.db import Database
from mapserver.store.import_msr import ImportResult
from mapserver.store.mapio import load_map, save_map

FORMAT = "g2o"
MAX_TILT_RAD = 0.01


@dataclass(frozen=True)
class PosesImport(ImportResult):
    """What ``import --format g2o`` changed: the map, its experience count and the largest move (m)."""

    max_shift_m: float = 0.0

    def summary(self) -> dict[str, Any]:
        """Return the ``import --json`` object (contract keys plus ``max_shift_m`` and ``notes``)."""
        return {**super().summary(), "max_shift_m": self.max_shift_m}


def _poses_for_map(path: Path, stored: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Return the map's new (E, 4) poses from the file's vertices, checked against the stored ones."""
    vertices = read_g2o_vertices(path)
    n = stored.shape[0]
    expected = np.arange(n)
    order = np.argsort(vertices.ids)
    ids = vertices.ids[order]
    if ids.shape[0] != n or not np.array_equal(ids, expected):
        extra = sorted(set(ids.tolist()) - set(expected.tolist()))
        lacking = sorted(set(expected.tolist()) - set(ids.tolist()))
        what = f"lacks vertex {lacking[0]}" if lacking else f"has vertex {extra[0]}, which is no experience"
        msg = f"{path}: the map has {n} experiences (ids 0..{n - 1}) but the file {what}"
        raise InputError(msg)
    if vertices.max_tilt_rad > MAX_TILT_RAD:
        msg = (
            f"{path}: a vertex is tilted by {vertices.max_tilt_rad:.3g} rad (roll or pitch); a RatSLAM map holds "
            f"yaw only (at most {MAX_TILT_RAD} rad is dropped)"
        )
        raise InputError(msg)
    poses = vertices.poses[order].copy()
    notes = []
    if vertices.kind == "VERTEX_SE2":
        poses[:, 2] = stored[:, 2]
        notes.append("SE2 vertices: z kept as stored")
    elif vertices.max_tilt_rad > 0.0:
        notes.append(f"roll/pitch up to {vertices.max_tilt_rad:.3g} rad dropped (yaw kept)")
    return poses, notes


def import_g2o_poses(db: Database, *, path: str | Path, map_name: str) -> PosesImport:
    """Replace the experience poses of stored map ``map_name`` with the vertices of a g2o file.

    Raises:
        InputError: unreadable or malformed file, vertices that do not match the map's experiences, or
            tilted SE3 vertices.
        UnknownMapError: no such map.
        StaleMapError: the map changed while the file was read.
    """
    file = Path(path)
    if not file.is_file():
        msg = f"g2o file not found: {str(file)!r}"
        raise InputError(msg)
    content = load_map(db, name=map_name)
    snapshot = {k: np.array(v) for k, v in content.snapshot.items()}
    stored = np.asarray(snapshot["em_pose"], dtype=np.float64).reshape(-1, 4)
    poses, notes = _poses_for_map(file, stored)
    snapshot["em_pose"] = poses
    meta = content.meta
    save_map(
        db,
        name=map_name,
        params=content.params,
        snapshot=snapshot,
        sessions=[s.id for s in meta.sessions],
        expected_version=meta.map.version,
        template_index=meta.template_index,
        experience_index=meta.experience_index,
    )
    shift = float(np.max(np.linalg.norm(poses[:, :3] - stored[:, :3], axis=1))) if stored.shape[0] else 0.0
    notes.append("links keep their measured transforms; a session continuing this map relaxes towards them")
    return PosesImport(
        map=map_name,
        experiences=int(stored.shape[0]),
        links=int(np.asarray(snapshot["em_link_from"]).shape[0]),
        templates=int(np.asarray(snapshot["lv_templates"]).shape[0]),
        max_shift_m=shift,
        notes=tuple(notes),
    )

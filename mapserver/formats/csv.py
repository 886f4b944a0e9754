"""A map as two CSV tables for spreadsheets: experiences and links (RFC 4180, header row, ``,`` separated).

* experiences: ``id, session, template, stamp, x, y, z, yaw, qx, qy, qz, qw`` (one row per experience,
  in id order; the quaternion is the rotation by ``yaw`` about z);
* links: ``from, to, kind, dt, distance, dx, dy, dz, dyaw`` (+ ``active`` when the map's links carry
  that flag): ``dx … dyaw`` is the pose of ``to`` in the frame of ``from``.

Numbers are written as Python's shortest round-trip text, so reading them back gives the same float64.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping

import numpy as np
import numpy.typing as npt

from core.se3 import quaternions_from_yaws
from mapserver.formats import link_kind_name

EXPERIENCE_COLUMNS = ("id", "session", "template", "stamp", "x", "y", "z", "yaw", "qx", "qy", "qz", "qw")
LINK_COLUMNS = ("from", "to", "kind", "dt", "distance", "dx", "dy", "dz", "dyaw")


def _csv(header: tuple[str, ...], rows: list[list[object]]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\r\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buffer.getvalue()


def experiences_csv(snapshot: Mapping[str, npt.ArrayLike], session_names: Mapping[int, str]) -> str:
    """Return the experiences table of a snapshot (``session`` empty when its origin has no name)."""
    pose = np.asarray(snapshot["em_pose"], dtype=np.float64).reshape(-1, 4)
    templates = np.asarray(snapshot["em_template"]).reshape(-1).tolist()
    stamps = np.asarray(snapshot["em_stamp"], dtype=np.float64).reshape(-1).tolist()
    origins = np.asarray(snapshot["em_origin"]).reshape(-1).tolist()
    quaternions = quaternions_from_yaws(pose[:, 3])
    qz, qw = quaternions[:, 2].tolist(), quaternions[:, 3].tolist()
    rows: list[list[object]] = [
        [i, session_names.get(int(origins[i]), ""), int(templates[i]), stamps[i], *p, 0.0, 0.0, qz[i], qw[i]]
        for i, p in enumerate(pose.tolist())
    ]
    return _csv(EXPERIENCE_COLUMNS, rows)


def links_csv(snapshot: Mapping[str, npt.ArrayLike]) -> str:
    """Return the links table of a snapshot (with ``active`` when ``em_link_active`` exists)."""
    src = np.asarray(snapshot["em_link_from"]).reshape(-1).tolist()
    dst = np.asarray(snapshot["em_link_to"]).reshape(-1).tolist()
    kinds = np.asarray(snapshot["em_link_kind"]).reshape(-1).tolist()
    dt = np.asarray(snapshot["em_link_dt"], dtype=np.float64).reshape(-1).tolist()
    dist = np.asarray(snapshot["em_link_distance"], dtype=np.float64).reshape(-1).tolist()
    tf = np.asarray(snapshot["em_link_transform"], dtype=np.float64).reshape(-1, 4).tolist()
    rows: list[list[object]] = [
        [int(src[k]), int(dst[k]), link_kind_name(int(kinds[k])) or str(kinds[k]), dt[k], dist[k], *tf[k]]
        for k in range(len(src))
    ]
    header: tuple[str, ...] = LINK_COLUMNS
    if "em_link_active" in snapshot:
        active = np.asarray(snapshot["em_link_active"], dtype=bool).reshape(-1).tolist()
        header = (*LINK_COLUMNS, "active")
        rows = [[*row, "true" if on else "false"] for row, on in zip(rows, active, strict=True)]
    return _csv(header, rows)

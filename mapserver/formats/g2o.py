"""The experience graph as a g2o file (read by g2o, GTSAM's ``readG2o``, Ceres' pose-graph examples).

Writing (:func:`g2o_text`): one vertex per experience (id = experience id, pose = its map pose) and one edge
per link (measurement = the link's transform, the pose of ``to`` in the frame of ``from``), then ``FIX 0``
(the map's anchor, which relaxation never moves either).

* Planar maps (3-DoF lattice): ``VERTEX_SE2 id x y yaw`` and ``EDGE_SE2 from to dx dy dyaw`` + the upper
  triangle of the 3 × 3 information matrix (order x, y, θ).
* 4-DoF maps: ``VERTEX_SE3:QUAT id x y z qx qy qz qw`` and ``EDGE_SE3:QUAT from to dx dy dz qx qy qz qw``
  + the upper triangle of the 6 × 6 information matrix (order x, y, z, roll, pitch, yaw).

**Information rule** (diagonal; a link's measured odometry drifts with the distance ``d`` it spans):
σ_xy = σ_z = 0.02 m + 0.05 · d, σ_yaw = 0.01 rad + 0.05 rad/m · d, and, for SE3, σ_roll = σ_pitch =
0.001 rad (RatSLAM maps hold no roll or pitch). Information = 1/σ², the rotation block on rotation angles
as GTSAM's ``readG2o`` and Ceres' pose-graph example read it (checked: GTSAM 4 reads σ back from these
files). g2o's own ``EdgeSE3`` applies that block to the quaternion's vector part, half the angle, so under
g2o the rotation terms weigh 4 × more relative to translation; the poses' fixed point is unchanged for a
graph whose links agree.

A link switched off by relaxation (``em_link_active`` false, when the snapshot has that array) is
written as a comment line ``# inactive EDGE_...`` at the end of the file, after ``FIX 0``: g2o skips
comments, and GTSAM's ``readG2o`` (4.3) stops reading at the first line it does not know, so nothing that
matters comes after one (tests/mapserver/test_formats_g2o.py reads an export whole with the PyPI package).
A link's kind is not part of an edge; the manual links (added by an operator, ``mapserver link``) are named last,
one comment line ``# manual FROM TO`` each (:func:`manual_lines`).

Reading (:func:`read_g2o_vertices`): the vertices of a file (SE2 or SE3:QUAT) as poses ``[x, y, z, yaw]``;
edges, ``FIX`` and comments are skipped. An SE3 vertex's yaw is that of its rotation; its roll and pitch
(which a 4-DoF map cannot hold) are returned so the caller can report them. A vertex with a value that is not
finite, a coordinate beyond ``MAX_POSITION_M`` (1e8 m) or an SE2 angle beyond ``MAX_ANGLE_RAD`` (1e6 rad) is
refused, naming the line and the field (the bounds of :mod:`mapserver.bounds`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from core.links import LinkKind
from core.se3 import quaternions_from_yaws, yaw_of_unit_quaternion
from mapserver.bounds import MAX_ANGLE_RAD, MAX_POSITION_M, value_problem
from mapserver.errors import InputError

SIGMA_XY_M = 0.02
SIGMA_XY_PER_M = 0.05
SIGMA_YAW_RAD = 0.01
SIGMA_YAW_PER_M = 0.05
SIGMA_TILT_RAD = 0.001


def link_sigmas(distance: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Return (σ_xy, σ_yaw) per link from its distance (the module docstring's rule)."""
    d = np.abs(np.asarray(distance, dtype=np.float64))
    return SIGMA_XY_M + SIGMA_XY_PER_M * d, SIGMA_YAW_RAD + SIGMA_YAW_PER_M * d


def _upper(info: np.ndarray) -> np.ndarray:
    """Rows of the upper triangles (row-major) of a stack of (n, k, k) matrices."""
    rows, cols = np.triu_indices(info.shape[1])
    return info[:, rows, cols]


def information_se2(distance: npt.ArrayLike) -> np.ndarray:
    """(L, 3, 3) information matrices of SE2 edges (order x, y, θ)."""
    s_xy, s_yaw = link_sigmas(distance)
    info = np.zeros((s_xy.shape[0], 3, 3))
    info[:, 0, 0] = info[:, 1, 1] = 1.0 / s_xy**2
    info[:, 2, 2] = 1.0 / s_yaw**2
    return info


def information_se3(distance: npt.ArrayLike) -> np.ndarray:
    """(L, 6, 6) information matrices of SE3:QUAT edges (order x, y, z, roll, pitch, yaw)."""
    s_xy, s_yaw = link_sigmas(distance)
    info = np.zeros((s_xy.shape[0], 6, 6))
    info[:, 0, 0] = info[:, 1, 1] = info[:, 2, 2] = 1.0 / s_xy**2
    info[:, 3, 3] = info[:, 4, 4] = 1.0 / SIGMA_TILT_RAD**2
    info[:, 5, 5] = 1.0 / s_yaw**2
    return info


def _numbers(values: np.ndarray) -> list[str]:
    """Format each row of ``values`` as space-separated shortest round-trip floats."""
    return [" ".join(repr(float(v)) for v in row) for row in values.tolist()]


def vertex_lines(ids: npt.ArrayLike, pose: np.ndarray, *, planar: bool) -> list[str]:
    """Return the vertex lines (each ending in a newline) of experiences ``ids`` at poses ``pose`` (n, 4)."""
    pose = np.asarray(pose, dtype=np.float64).reshape(-1, 4)
    if planar:
        values, tag = np.column_stack([pose[:, 0], pose[:, 1], pose[:, 3]]), "VERTEX_SE2"
    else:
        values = np.column_stack([pose[:, :3], quaternions_from_yaws(pose[:, 3])])
        tag = "VERTEX_SE3:QUAT"
    ids_list = np.asarray(ids, dtype=np.int64).reshape(-1).tolist()
    return [f"{tag} {i} {v}\n" for i, v in zip(ids_list, _numbers(values), strict=True)]


def edge_lines(
    src: npt.ArrayLike, dst: npt.ArrayLike, tf: np.ndarray, distance: npt.ArrayLike, *, planar: bool,
    inactive: bool = False,
) -> list[str]:  # fmt: skip
    """Return the edge lines (each ending in a newline) of links ``src`` → ``dst`` with transforms ``tf`` (n, 4).

    ``inactive``: the links are switched off, and each line is written as the comment ``# inactive EDGE_…``.
    """
    tf = np.asarray(tf, dtype=np.float64).reshape(-1, 4)
    if planar:
        values = np.column_stack([tf[:, 0], tf[:, 1], tf[:, 3], _upper(information_se2(distance))])
        tag = "EDGE_SE2"
    else:
        values = np.column_stack([tf[:, :3], quaternions_from_yaws(tf[:, 3]), _upper(information_se3(distance))])
        tag = "EDGE_SE3:QUAT"
    prefix = "# inactive " if inactive else ""
    ends = zip(np.asarray(src).reshape(-1).tolist(), np.asarray(dst).reshape(-1).tolist(), strict=True)
    return [f"{prefix}{tag} {s} {t} {m}\n" for (s, t), m in zip(ends, _numbers(values), strict=True)]


def manual_lines(src: npt.ArrayLike, dst: npt.ArrayLike) -> list[str]:
    """Return ``# manual FROM TO`` for each manual link ``src`` → ``dst`` (comments: g2o and GTSAM skip them)."""
    ends = zip(np.asarray(src).reshape(-1).tolist(), np.asarray(dst).reshape(-1).tolist(), strict=True)
    return [f"# manual {s} {t}\n" for s, t in ends]


def g2o_text(snapshot: Mapping[str, npt.ArrayLike], *, planar: bool) -> str:
    """Return the g2o file of a map snapshot (``em_pose``, ``em_link_*``; see the module docstring).

    Args:
        snapshot: engine snapshot arrays.
        planar: write SE2 (3-DoF maps) instead of SE3:QUAT.
    """
    pose = np.asarray(snapshot["em_pose"], dtype=np.float64).reshape(-1, 4)
    src = np.asarray(snapshot["em_link_from"], dtype=np.int64).reshape(-1)
    dst = np.asarray(snapshot["em_link_to"], dtype=np.int64).reshape(-1)
    tf = np.asarray(snapshot["em_link_transform"], dtype=np.float64).reshape(-1, 4)
    dist = np.asarray(snapshot["em_link_distance"], dtype=np.float64).reshape(-1)
    active = np.asarray(snapshot.get("em_link_active", np.ones(src.shape[0], dtype=bool)), dtype=bool)
    lines = vertex_lines(np.arange(pose.shape[0]), pose, planar=planar)
    lines += edge_lines(src[active], dst[active], tf[active], dist[active], planar=planar)
    if pose.shape[0]:
        lines.append("FIX 0\n")
    off = ~active
    lines += edge_lines(src[off], dst[off], tf[off], dist[off], planar=planar, inactive=True)
    kind = np.asarray(snapshot.get("em_link_kind", np.zeros(0)), dtype=np.int64).reshape(-1)[: src.shape[0]]
    manual = np.zeros(src.shape[0], dtype=bool)
    manual[: kind.size] = kind == int(LinkKind.MANUAL)
    lines += manual_lines(src[manual], dst[manual])
    return "".join(lines) if lines else "\n"


@dataclass(frozen=True)
class G2oVertices:
    """The vertices of a g2o file: ids, poses ``[x, y, z, yaw]`` and (SE3) the largest roll/pitch seen."""

    ids: np.ndarray
    poses: np.ndarray
    kind: str
    max_tilt_rad: float


def _yaw_and_tilt(q: np.ndarray) -> tuple[float, float]:
    """Yaw (about z, ZYX convention) and the larger of |roll|, |pitch| of a unit quaternion (x, y, z, w)."""
    scaled = q / np.max(np.abs(q))  # no overflow in the norm of huge components
    x, y, z, w = (scaled / np.linalg.norm(scaled)).tolist()
    yaw = yaw_of_unit_quaternion(x, y, z, w)
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    return yaw, max(abs(roll), abs(pitch))


def _check_vertex_bounds(tag: str, values: list[float], where: str) -> None:
    """Refuse a vertex whose position is beyond ``MAX_POSITION_M`` or whose SE2 angle is beyond ``MAX_ANGLE_RAD``.

    Every value must be finite; a quaternion is only normalised (:func:`_yaw_and_tilt`). The bounds are those of
    :mod:`mapserver.bounds`; the message names the field.
    """
    if not all(math.isfinite(v) for v in values):
        msg = f"{where}: {tag} holds a non-finite value"
        raise InputError(msg)
    names = ("x", "y", "theta") if tag == "VERTEX_SE2" else ("x", "y", "z")
    for name, value in zip(names, values, strict=False):
        bound, unit = (MAX_ANGLE_RAD, "rad") if name == "theta" else (MAX_POSITION_M, "m")
        problem = value_problem(value, bound, unit)
        if problem is not None:
            msg = f"{where}: {tag} {name} {problem}"
            raise InputError(msg)


def _vertex(tag: str, fields: list[str], where: str) -> tuple[int, list[float], float]:
    """Parse one vertex line's fields (after the tag) into (id, [x, y, z, yaw], tilt)."""
    expected = 4 if tag == "VERTEX_SE2" else 8
    if len(fields) != expected:
        msg = f"{where}: {tag} needs {expected} values (id and pose), found {len(fields)}"
        raise InputError(msg)
    try:
        ident = int(fields[0])
        values = [float(v) for v in fields[1:]]
    except ValueError:
        msg = f"{where}: {tag} holds a value that is not a number"
        raise InputError(msg) from None
    _check_vertex_bounds(tag, values, where)
    if tag == "VERTEX_SE2":
        return ident, [values[0], values[1], 0.0, values[2]], 0.0
    q = np.asarray(values[3:7])
    if np.max(np.abs(q)) < 1e-9 and np.linalg.norm(q) < 1e-9:  # the norm alone may overflow
        msg = f"{where}: {tag} has a zero quaternion"
        raise InputError(msg)
    yaw, tilt = _yaw_and_tilt(q)
    return ident, [values[0], values[1], values[2], yaw], tilt


def read_g2o_vertices(path: str | Path) -> G2oVertices:
    """Read the vertices of a g2o file (see the module docstring).

    Raises:
        InputError: unreadable file, a malformed vertex line (named ``file:line``), a repeated id, SE2 and
            SE3 vertices mixed, or no vertex at all.
    """
    file = Path(path)
    try:
        text = file.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        msg = f"cannot read g2o file {str(file)!r}: {err}"
        raise InputError(msg) from None
    ids: list[int] = []
    poses: list[list[float]] = []
    kinds: set[str] = set()
    tilt = 0.0
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#") or not fields[0].startswith("VERTEX_"):
            continue
        tag = fields[0]
        if tag not in ("VERTEX_SE2", "VERTEX_SE3:QUAT"):
            msg = f"{file}:{number}: unsupported vertex type {tag!r} (VERTEX_SE2 or VERTEX_SE3:QUAT)"
            raise InputError(msg)
        ident, pose, vertex_tilt = _vertex(tag, fields[1:], f"{file}:{number}")
        kinds.add(tag)
        ids.append(ident)
        poses.append(pose)
        tilt = max(tilt, vertex_tilt)
    if not ids:
        msg = f"{file}: no VERTEX_SE2 or VERTEX_SE3:QUAT line"
        raise InputError(msg)
    if len(kinds) > 1:
        msg = f"{file}: mixes VERTEX_SE2 and VERTEX_SE3:QUAT vertices"
        raise InputError(msg)
    id_array = np.asarray(ids, dtype=np.int64)
    unique, counts = np.unique(id_array, return_counts=True)
    if np.any(counts > 1):
        msg = f"{file}: vertex id {int(unique[counts > 1][0])} appears more than once"
        raise InputError(msg)
    return G2oVertices(ids=id_array, poses=np.asarray(poses), kind=kinds.pop(), max_tilt_rad=tilt)

"""Map JSON (``mapserver-map/1``) and TUM trajectory files: building, reading and writing them.

The public contract for both formats is ``docs/interfaces.md`` (shared): a map JSON holds the effective
parameters, the sessions, the template count, the experiences (SE(3) pose as position + unit quaternion, plus
``yaw``) and the links; a TUM file holds one ``timestamp x y z qx qy qz qw`` line per pose.

Extensions written here (consumers must ignore keys they do not know): every link also carries
``"transform": [dx, dy, dz, dyaw]`` (pose of ``to`` in the frame of ``from``), and a map may carry
``"odometry": [[stamp, x, y, z], ...]``, the raw dead-reckoning position of every processed frame, which
:mod:`mapserver.evaluation` uses for the odometry baseline, and ``"frames": [[stamp, template, created],
...]``, per processed frame its stamp (s), the id of the template it matched or created, and 1 when the
template was created at that frame (else 0), which the evaluation uses for place-recognition rates.

Every writer is atomic: it writes a temporary file in the destination's directory and ``os.replace``-s it.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from core import LinkKind
from core.se3 import quaternions_from_yaws
from mapserver.bounds import MAX_ANGLE_RAD, MAX_POSITION_M, MAX_TIME_S, value_problem
from mapserver.errors import InputError, MapServerError

MAP_FORMAT = "mapserver-map/1"
"""Value of the ``format`` key of every map JSON this module writes and accepts."""

LINK_KIND_NAMES: tuple[str, ...] = tuple(kind.name.lower() for kind in sorted(LinkKind))
"""Link ``kind`` names (map JSON, CSV, the store's ``links.kind``, the viewer): ``core.LinkKind``'s names in lower
case, indexed by the kind's code (``em_link_kind``)."""

LINK_KIND_CODES: dict[str, int] = {name: code for code, name in enumerate(LINK_KIND_NAMES)}
"""Link ``kind`` name → its code: the inverse of :data:`LINK_KIND_NAMES`."""

TUM_HEADER = "# timestamp x y z qx qy qz qw"

_TOP_KEYS = ("format", "params", "sessions", "templates", "experiences", "links")
_EXPERIENCE_KEYS = ("id", "x", "y", "z", "qx", "qy", "qz", "qw", "yaw", "template", "stamp", "session")
_EXPERIENCE_NUMBERS = ("id", "x", "y", "z", "qx", "qy", "qz", "qw", "yaw", "template", "stamp")
_LINK_KEYS = ("from", "to", "dt", "distance", "kind")
_BOUNDS: dict[str, tuple[float, str]] = {
    "x": (MAX_POSITION_M, "m"), "y": (MAX_POSITION_M, "m"), "z": (MAX_POSITION_M, "m"), "yaw": (MAX_ANGLE_RAD, "rad"),
    "stamp": (MAX_TIME_S, "s"), "dt": (MAX_TIME_S, "s"), "distance": (MAX_POSITION_M, "m"),
}  # fmt: skip
"""Bounds (magnitude, unit) of map JSON numbers (:mod:`mapserver.bounds`); other numbers need only be finite."""
_SESSION_KEYS = ("name", "log_sha256", "frames")

PathLike = str | os.PathLike[str]


@dataclass(frozen=True, slots=True)
class SessionInfo:
    """One session of a map as listed in the map JSON.

    Attributes:
        name: session name (unique within the map).
        log_sha256: hex SHA-256 of the mission log the session was built from.
        frames: number of frames processed.

    """

    name: str
    log_sha256: str
    frames: int


@dataclass(frozen=True)
class Trajectory:
    """A timed sequence of SE(3) poses.

    Attributes:
        stamps_s: (N,) float64 times in seconds.
        positions_xyz: (N, 3) float64 positions in metres.
        quat_xyzw: (N, 4) float64 unit quaternions (x, y, z, w).

    """

    stamps_s: npt.NDArray[np.float64]
    positions_xyz: npt.NDArray[np.float64]
    quat_xyzw: npt.NDArray[np.float64]

    def __post_init__(self) -> None:
        stamps = np.asarray(self.stamps_s, dtype=np.float64).reshape(-1)
        n = stamps.shape[0]
        positions = np.asarray(self.positions_xyz, dtype=np.float64).reshape(n, 3)
        quats = np.asarray(self.quat_xyzw, dtype=np.float64).reshape(n, 4)
        object.__setattr__(self, "stamps_s", stamps)
        object.__setattr__(self, "positions_xyz", positions)
        object.__setattr__(self, "quat_xyzw", quats)

    def __len__(self) -> int:
        return int(self.stamps_s.shape[0])

    def sorted(self) -> Trajectory:
        """Return the trajectory in stamp order (stable, so equal stamps keep their order)."""
        order = np.argsort(self.stamps_s, kind="stable")
        if np.array_equal(order, np.arange(len(self))):
            return self
        return Trajectory(self.stamps_s[order], self.positions_xyz[order], self.quat_xyzw[order])


# ----------------------------------------------------------------------------------------------- map JSON


def _plain(value: Any) -> Any:
    """Convert numpy scalars/arrays, tuples and mappings to plain JSON-able Python values."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    return value


def map_json(
    *,
    params: Mapping[str, Any],
    snapshot: Mapping[str, npt.NDArray[Any]],
    sessions: Sequence[SessionInfo],
    session_name_by_origin: Mapping[int, str],
    odometry: npt.ArrayLike | None = None,
    frames: Sequence[Sequence[float]] | None = None,
) -> dict[str, Any]:
    """Build the contract's map JSON document from an engine snapshot.

    Experience ids are the snapshot's row indices; the quaternion is the rotation by the experience's yaw
    about z (RatSLAM maps are 4-DoF: x, y, z, yaw). Every value is a plain Python ``int``/``float``/``str``.

    Args:
        params: effective parameters (``Params.to_dict()``); numpy values are converted.
        snapshot: ``core.Engine.snapshot()`` arrays (see ``docs/architecture.md``); uses ``lv_means``,
            ``em_pose``, ``em_template``, ``em_stamp``, ``em_origin`` and the ``em_link_*`` arrays.
        sessions: the map's sessions, in order.
        session_name_by_origin: ``em_origin`` tag → session name. An origin missing from it gives
            ``"session": null``.
        odometry: optional (N, 4) ``[stamp, x, y, z]`` raw dead-reckoning positions per frame; written as
            the ``"odometry"`` extension key when given.
        frames: optional ``(stamp, template, created)`` per processed frame; written as the ``"frames"``
            extension key when given (``created`` as 0/1).

    Returns:
        ``{"format", "params", "sessions", "templates", "experiences", "links"}`` (+ ``"odometry"``,
        ``"frames"``).

    Raises:
        ValueError: a link kind code is unknown, or ``odometry`` or ``frames`` has the wrong shape.

    """
    if "lv_means" in snapshot:
        n_templates = int(np.asarray(snapshot["lv_means"]).shape[0])
    else:
        n_templates = int(np.asarray(snapshot["lv_templates"]).shape[0])
    doc: dict[str, Any] = {
        "format": MAP_FORMAT,
        "params": _plain(dict(params)),
        "sessions": [
            {"name": str(s.name), "log_sha256": str(s.log_sha256), "frames": int(s.frames)} for s in sessions
        ],
        "templates": n_templates,
        "experiences": _experiences_json(snapshot, session_name_by_origin),
        "links": _links_json(snapshot),
    }
    if odometry is not None:
        odo = np.asarray(odometry, dtype=np.float64)
        if odo.ndim != 2 or odo.shape[1] != 4:
            msg = f"odometry must have shape (N, 4) [stamp, x, y, z], got {odo.shape!r}"
            raise ValueError(msg)
        doc["odometry"] = odo.tolist()
    if frames is not None:
        doc["frames"] = _frames_json(frames)
    return doc


def _experiences_json(
    snapshot: Mapping[str, npt.NDArray[Any]], session_name_by_origin: Mapping[int, str]
) -> list[dict[str, Any]]:
    """Return the map JSON's ``experiences``: pose, yaw quaternion about z, template, stamp and session name."""
    pose = np.asarray(snapshot["em_pose"], dtype=np.float64).reshape(-1, 4)
    templates = np.asarray(snapshot["em_template"]).reshape(-1).tolist()
    stamps = np.asarray(snapshot["em_stamp"], dtype=np.float64).reshape(-1).tolist()
    origins = np.asarray(snapshot["em_origin"]).reshape(-1).tolist()
    quaternions = quaternions_from_yaws(pose[:, 3])
    qz = quaternions[:, 2].tolist()
    qw = quaternions[:, 3].tolist()
    xyz_yaw = pose.tolist()
    return [
        {
            "id": i,
            "x": xyz_yaw[i][0],
            "y": xyz_yaw[i][1],
            "z": xyz_yaw[i][2],
            "qx": 0.0,
            "qy": 0.0,
            "qz": qz[i],
            "qw": qw[i],
            "yaw": xyz_yaw[i][3],
            "template": int(templates[i]),
            "stamp": stamps[i],
            "session": session_name_by_origin.get(int(origins[i])),
        }
        for i in range(pose.shape[0])
    ]


def link_kind_name(code: int) -> str | None:
    """Return the name of link kind ``code`` (:data:`LINK_KIND_NAMES`), None for a code no kind has."""
    return LINK_KIND_NAMES[code] if 0 <= code < len(LINK_KIND_NAMES) else None


def _links_json(snapshot: Mapping[str, npt.NDArray[Any]]) -> list[dict[str, Any]]:
    """Return the map JSON's ``links``; a link switched off by robust relaxation carries ``"active": false``.

    Raises:
        ValueError: a link kind code is unknown.
    """
    link_from = np.asarray(snapshot["em_link_from"]).reshape(-1).tolist()
    link_to = np.asarray(snapshot["em_link_to"]).reshape(-1).tolist()
    link_dt = np.asarray(snapshot["em_link_dt"], dtype=np.float64).reshape(-1).tolist()
    link_dist = np.asarray(snapshot["em_link_distance"], dtype=np.float64).reshape(-1).tolist()
    link_kind = np.asarray(snapshot["em_link_kind"]).reshape(-1).tolist()
    link_tf = np.asarray(snapshot["em_link_transform"], dtype=np.float64).reshape(-1, 4).tolist()
    link_off = set(np.flatnonzero(~np.asarray(snapshot.get("em_link_active", np.ones(0, bool)), dtype=bool)).tolist())
    links = []
    for k in range(len(link_from)):
        kind = link_kind_name(int(link_kind[k]))
        if kind is None:
            msg = f"unknown em_link_kind {link_kind[k]!r} on link {k}"
            raise ValueError(msg)
        links.append(
            {
                "from": int(link_from[k]),
                "to": int(link_to[k]),
                "dt": link_dt[k],
                "distance": link_dist[k],
                "kind": kind,
                "transform": link_tf[k],
            }
        )
        if k in link_off:  # switched off by robust relaxation (stays stored)
            links[-1]["active"] = False
    return links


def _frames_json(frames: Sequence[Sequence[float]]) -> list[list[float | int]]:
    """Return the ``frames`` extension rows ``[stamp, template, created (0/1)]``.

    Raises:
        ValueError: a row is not (stamp, template, created).
    """
    rows: list[list[float | int]] = []
    for row in frames:
        if len(row) != 3:
            msg = f"frames rows must be (stamp, template, created), got {row!r}"
            raise ValueError(msg)
        rows.append([float(row[0]), int(row[1]), 1 if row[2] else 0])
    return rows


def _process_umask() -> int:
    """Return the process's umask: read from ``/proc/self/status`` (Linux), else set and restored at once.

    Read once, at import, while nothing else runs: ``os.umask`` changes it for every thread.
    """
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


FILE_MODE = 0o666 & ~_process_umask()
"""The mode of every file mapserver writes: what ``open`` would give under the umask (``mkstemp`` gives 0600)."""


def _temporary_beside(target: Path) -> tuple[int, str]:
    """Return (fd, name) of a new temporary file in ``target``'s directory, with the mode of :data:`FILE_MODE`."""
    directory = target.parent if str(target.parent) else Path(".")
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=directory)
    try:
        os.fchmod(fd, FILE_MODE)
    except BaseException:
        os.close(fd)
        os.unlink(tmp_name)
        raise
    return fd, tmp_name


def atomic_write_bytes(path: PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically: temporary file in the same directory, fsync, ``os.replace``.

    The file gets the mode a plain ``open`` would give it under the process's umask (:data:`FILE_MODE`).

    Args:
        path: destination file; its directory must exist.
        data: the complete file content.

    """
    atomic_write_chunks(path, (data,))


def atomic_write_chunks(path: PathLike, chunks: Iterable[bytes]) -> int:
    """Write ``chunks`` to ``path`` atomically (see :func:`atomic_write_bytes`); return the bytes written.

    Args:
        path: destination file; its directory must exist.
        chunks: the file's content in pieces (never held whole).

    """
    target = Path(path)
    fd, tmp_name = _temporary_beside(target)
    written = 0
    try:
        with os.fdopen(fd, "wb") as handle:
            for chunk in chunks:
                handle.write(chunk)
                written += len(chunk)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp_name, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise
    return written


def write_map_json(path: PathLike, doc: Mapping[str, Any]) -> None:
    """Write a map JSON document atomically as UTF-8.

    Args:
        path: destination file; its directory must exist.
        doc: the document (numpy values are converted to plain Python values).

    Raises:
        MapServerError: the document holds NaN or an infinity (not valid JSON) or a non-JSON value.

    """
    try:
        text = json.dumps(_plain(doc), ensure_ascii=False, allow_nan=False, separators=(",", ":"))
    except (ValueError, TypeError) as err:
        msg = f"cannot write map JSON {str(path)!r}: {err}"
        raise MapServerError(msg) from err
    atomic_write_bytes(path, (text + "\n").encode("utf-8"))


def _reject_constant(token: str) -> Any:
    msg = f"non-finite number {token!r}"
    raise ValueError(msg)


def _finite_float(token: str) -> float:
    """Parse a JSON number that is written as a float; one beyond the float range (``1e400``) is refused."""
    value = float(token)
    if not math.isfinite(value):
        msg = f"number {token[:40]!r} is beyond the float range"
        raise ValueError(msg)
    return value


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def read_map_json(path: PathLike) -> dict[str, Any]:
    """Read and validate a map JSON file.

    Checks the ``format`` key, the presence of every top-level key of the contract, the keys of every
    session, experience and link, that experience numbers are numbers, that no number is beyond the float range
    (``1e400``), that positions, yaws, stamps, link ``dt`` and ``distance`` keep the bounds of
    :mod:`mapserver.bounds`, and that link endpoints name experiences of the map.

    Args:
        path: the map JSON file.

    Returns:
        The parsed document.

    Raises:
        InputError: the file is missing, unreadable, not JSON, or does not follow ``mapserver-map/1``; the
            message is one line naming the reason.

    """
    name = str(path)
    doc = _parse_map_file(path, name)
    _check_top_level(name, doc)
    _check_items(name, "sessions", doc["sessions"], _SESSION_KEYS)
    _check_items(name, "experiences", doc["experiences"], _EXPERIENCE_KEYS)
    _check_items(name, "links", doc["links"], _LINK_KEYS)
    _check_experiences_and_links(name, doc)
    if "odometry" in doc:
        _check_rows(name, doc, "odometry", ("stamp", "x", "y", "z"))
    if "frames" in doc:
        _check_rows(name, doc, "frames", ("stamp", "template", "created"))
    return doc


def _parse_map_file(path: PathLike, name: str) -> Any:
    """Return the JSON value of a map file (any JSON value; non-finite constants refused)."""
    try:
        raw = Path(path).read_bytes()
    except FileNotFoundError:
        msg = f"map file not found: {name!r}"
        raise InputError(msg) from None
    except OSError as err:
        msg = f"cannot read map file {name!r}: {err.strerror or err}"
        raise InputError(msg) from None
    try:
        return json.loads(raw.decode("utf-8"), parse_constant=_reject_constant, parse_float=_finite_float)
    except UnicodeDecodeError as err:
        msg = f"map file {name!r} is not UTF-8: {err.reason} at byte {err.start}"
        raise InputError(msg) from None
    except json.JSONDecodeError as err:
        msg = f"map file {name!r} is not valid JSON: {err.msg} at line {err.lineno} column {err.colno}"
        raise InputError(msg) from None
    except ValueError as err:
        msg = f"map file {name!r} is not valid JSON: {err}"
        raise InputError(msg) from None


def _check_top_level(name: str, doc: Any) -> None:
    """Refuse a document that is not an object of this format with every top-level key of its type."""
    if not isinstance(doc, dict):
        msg = f"map file {name!r} is not a JSON object"
        raise InputError(msg)
    fmt = doc.get("format")
    if fmt != MAP_FORMAT:
        msg = f"map file {name!r} has format {fmt!r}, expected {MAP_FORMAT!r}"
        raise InputError(msg)
    missing = [k for k in _TOP_KEYS if k not in doc]
    if missing:
        msg = f"map file {name!r} lacks key(s) {', '.join(missing)}"
        raise InputError(msg)
    for key in ("sessions", "experiences", "links"):
        if not isinstance(doc[key], list):
            msg = f"map file {name!r}: {key!r} is not a list"
            raise InputError(msg)
    if not isinstance(doc["params"], dict):
        msg = f"map file {name!r}: 'params' is not an object"
        raise InputError(msg)
    if not _is_number(doc["templates"]):
        msg = f"map file {name!r}: 'templates' is not a number: {doc['templates']!r}"
        raise InputError(msg)


def _check_value(name: str, where: str, value: Any, bound: tuple[float, str] | None) -> None:
    """Refuse a value that is not a number, not finite, or beyond ``bound`` (magnitude, unit)."""
    if not _is_number(value):
        msg = f"map file {name!r}: {where} is not a number: {value!r}"
        raise InputError(msg)
    problem = value_problem(float(value), *(bound or (math.inf, "")))
    if problem is not None:
        msg = f"map file {name!r}: {where} {problem}".rstrip()
        raise InputError(msg)


def _check_experiences_and_links(name: str, doc: dict[str, Any]) -> None:
    """Refuse experience and link numbers that break :data:`_BOUNDS`, and link endpoints naming no experience."""
    ids = set()
    for i, exp in enumerate(doc["experiences"]):
        for key in _EXPERIENCE_NUMBERS:
            _check_value(name, f"experiences[{i}].{key}", exp[key], _BOUNDS.get(key))
        ids.add(exp["id"])
    for k, link in enumerate(doc["links"]):
        for key in ("from", "to"):
            if link[key] not in ids:
                msg = f"map file {name!r}: links[{k}].{key} = {link[key]!r} is not an experience id"
                raise InputError(msg)
        for key in ("dt", "distance"):
            _check_value(name, f"links[{k}].{key}", link[key], _BOUNDS[key])


def _check_rows(name: str, doc: dict[str, Any], key: str, columns: tuple[str, ...]) -> None:
    """Refuse ``doc[key]`` unless it is a list of rows of ``columns`` numbers."""
    rows = doc[key]
    ok = isinstance(rows, list) and all(
        isinstance(row, list) and len(row) == len(columns) and all(_is_number(v) for v in row) for row in rows
    )
    if not ok:
        msg = f"map file {name!r}: {key!r} is not a list of [{', '.join(columns)}]"
        raise InputError(msg)


def _check_items(name: str, key: str, items: list[Any], required: Sequence[str]) -> None:
    for i, item in enumerate(items):
        if not isinstance(item, dict):
            msg = f"map file {name!r}: {key}[{i}] is not an object"
            raise InputError(msg)
        missing = [k for k in required if k not in item]
        if missing:
            msg = f"map file {name!r}: {key}[{i}] lacks key(s) {', '.join(missing)}"
            raise InputError(msg)


def map_trajectory(doc: Mapping[str, Any]) -> Trajectory:
    """Return the experience poses of a map JSON document as a trajectory.

    Args:
        doc: a map JSON document (as from :func:`read_map_json` or :func:`map_json`).

    Returns:
        One pose per experience (stamp = the experience's ``stamp``), in stamp order; experiences with equal
        stamps keep the document's order.

    """
    exps = doc["experiences"]
    stamps = np.array([float(e["stamp"]) for e in exps], dtype=np.float64)
    positions = np.array([[e["x"], e["y"], e["z"]] for e in exps], dtype=np.float64).reshape(-1, 3)
    quats = np.array([[e["qx"], e["qy"], e["qz"], e["qw"]] for e in exps], dtype=np.float64).reshape(-1, 4)
    return Trajectory(stamps, positions, quats).sorted()


def odometry_trajectory(doc: Mapping[str, Any]) -> Trajectory | None:
    """Return the ``"odometry"`` extension of a map JSON document as a trajectory (None when absent).

    Args:
        doc: a map JSON document.

    Returns:
        Raw dead-reckoning positions per frame in stamp order (identity orientation), or None when the
        document has no (or an empty) ``"odometry"`` key.

    """
    rows = doc.get("odometry")
    if not rows:
        return None
    arr = np.asarray(rows, dtype=np.float64).reshape(-1, 4)
    quats = np.zeros((arr.shape[0], 4))
    quats[:, 3] = 1.0
    return Trajectory(arr[:, 0], arr[:, 1:4], quats).sorted()


# ----------------------------------------------------------------------------------------------- TUM


def _check_tum_bounds(name: str, lineno: int, values: list[float]) -> None:
    """Refuse a TUM line whose stamp is beyond ``MAX_TIME_S`` or a coordinate beyond ``MAX_POSITION_M``."""
    fields = (("timestamp", MAX_TIME_S, "s"), ("x", MAX_POSITION_M, "m"), ("y", MAX_POSITION_M, "m"),
              ("z", MAX_POSITION_M, "m"))  # fmt: skip
    for (field, bound, unit), value in zip(fields, values, strict=False):
        problem = value_problem(value, bound, unit)
        if problem is not None:
            msg = f"{name}:{lineno}: {field} {problem}"
            raise InputError(msg)


def read_tum(path: PathLike) -> Trajectory:
    """Read a TUM trajectory file (``timestamp x y z qx qy qz qw`` per line).

    Blank lines and lines starting with ``#`` are skipped; fields are separated by whitespace. The poses are
    returned in stamp order (stable).

    Args:
        path: the TUM file.

    Returns:
        The trajectory.

    Raises:
        InputError: the file is missing or unreadable, a line does not hold exactly 8 finite numbers (the
            message names the line number), a stamp is beyond ``MAX_TIME_S`` or a coordinate beyond
            ``MAX_POSITION_M`` (:mod:`mapserver.bounds`), or the file holds no pose.

    """
    name = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        msg = f"trajectory file not found: {name!r}"
        raise InputError(msg) from None
    except UnicodeDecodeError as err:
        msg = f"trajectory file {name!r} is not UTF-8 text: {err.reason} at byte {err.start}"
        raise InputError(msg) from None
    except OSError as err:
        msg = f"cannot read trajectory file {name!r}: {err.strerror or err}"
        raise InputError(msg) from None
    rows: list[list[float]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = stripped.split()
        if len(fields) != 8:
            msg = f"{name}:{lineno}: expected 8 fields 'timestamp x y z qx qy qz qw', got {len(fields)}"
            raise InputError(msg)
        try:
            values = [float(f) for f in fields]
        except ValueError:
            msg = f"{name}:{lineno}: not a number in {stripped!r}"
            raise InputError(msg) from None
        if not all(math.isfinite(v) for v in values):
            msg = f"{name}:{lineno}: non-finite value in {stripped!r}"
            raise InputError(msg)
        _check_tum_bounds(name, lineno, values)
        rows.append(values)
    if not rows:
        msg = f"trajectory file {name!r} holds no pose"
        raise InputError(msg)
    arr = np.asarray(rows, dtype=np.float64)
    return Trajectory(arr[:, 0], arr[:, 1:4], arr[:, 4:8]).sorted()


def write_tum(
    path: PathLike,
    stamps_s: npt.ArrayLike,
    positions_xyz: npt.ArrayLike,
    quat_xyzw: npt.ArrayLike,
) -> None:
    """Write a TUM trajectory file atomically.

    Stamps are written with ``%.9f`` (nanosecond resolution); positions and quaternion components with 17
    significant digits, so reading the file back gives the same float64 values.

    Args:
        path: destination file; its directory must exist.
        stamps_s: (N,) stamps in seconds.
        positions_xyz: (N, 3) positions.
        quat_xyzw: (N, 4) quaternions (x, y, z, w).

    Raises:
        ValueError: the shapes disagree.

    """
    stamps = np.asarray(stamps_s, dtype=np.float64).reshape(-1)
    n = stamps.shape[0]
    positions = np.asarray(positions_xyz, dtype=np.float64)
    quats = np.asarray(quat_xyzw, dtype=np.float64)
    if positions.shape != (n, 3) or quats.shape != (n, 4):
        msg = (
            f"shapes disagree: stamps {stamps.shape!r}, positions {positions.shape!r}, quats {quats.shape!r}"
        )
        raise ValueError(msg)
    lines = [TUM_HEADER]
    for t, p, q in zip(stamps.tolist(), positions.tolist(), quats.tolist(), strict=True):
        values = " ".join(f"{v:.17g}" for v in (*p, *q))
        lines.append(f"{t:.9f} {values}")
    atomic_write_bytes(path, ("\n".join(lines) + "\n").encode("utf-8"))

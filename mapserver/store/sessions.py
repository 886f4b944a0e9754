"""Sessions: one processed mission log (or imported map) each — provenance, progress, map membership."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

import numpy as np
import numpy.typing as npt
from sqlalchemy import Connection, insert, select, update

from mapserver import __version__
from mapserver.errors import NotFoundError
from mapserver.store.models import Session, utcnow

NAME_LIMIT = 200


@dataclass(frozen=True, slots=True)
class NewSession:
    """What is known about a session when it is first stored.

    Attributes:
        name: wanted name (made unique with a ``-2``, ``-3``... suffix if taken).
        log_name: the source file or directory name.
        log_sha256: SHA-256 of the source (see ``MissionLog.sha256``).
        topics: the topic mapping used (``{"image", "odometry", "ground_truth"}``); ``{}`` for imports.
        params: the effective engine parameters (``Params.to_dict()``).
        status: ``partial`` or ``complete``.
        frames_processed: frames run through the engine so far.
        frames_total: frames in the log (None when unknown).
        first_stamp: log time (s) of the first frame processed.
        last_stamp: log time (s) of the last frame processed.
        source: ``log`` or the import format (``multisession-ratslam``).
        origin: the tag this session's templates and experiences carry in the snapshot being saved
            (``lv_origin`` / ``em_origin``) until it has an id; ``0`` by convention.
        reckoning: optional (N, 4) ``[stamp, x, y, z]`` dead-reckoning positions per frame.
        reckoning_pose: optional final dead-reckoning pose ``[x, y, z, yaw]`` (to continue it).
        started_at: when processing the log began (UTC; None: now, for a session stored as it starts, or an
            import).
    """

    name: str
    log_name: str
    log_sha256: str
    topics: Mapping[str, Any]
    params: Mapping[str, Any]
    status: str = "complete"
    frames_processed: int = 0
    frames_total: int | None = None
    first_stamp: float | None = None
    last_stamp: float | None = None
    source: str = "log"
    origin: int = 0
    reckoning: npt.NDArray[np.float64] | None = field(default=None, compare=False)
    reckoning_pose: tuple[float, float, float, float] | None = None
    started_at: datetime | None = None


@dataclass(frozen=True, slots=True)
class SessionRecord:
    """A stored session (without its dead-reckoning blob; see :func:`get_reckoning`)."""

    id: int
    name: str
    map_id: int | None
    source: str
    log_name: str
    log_sha256: str
    topics: dict[str, Any]
    params: dict[str, Any]
    code_version: str
    status: str
    frames_processed: int
    frames_total: int | None
    first_stamp: float | None
    last_stamp: float | None
    started_at: datetime
    finished_at: datetime | None

    @property
    def complete(self) -> bool:
        """Return True when every frame of the log has been processed."""
        return self.status == "complete"

    @property
    def frames_per_s(self) -> float | None:
        """Return the frames processed per second of wall-clock time, start to finish (None: not finished)."""
        if self.finished_at is None:
            return None
        seconds = (self.finished_at - self.started_at).total_seconds()
        return self.frames_processed / seconds if seconds > 0 else None


_COLUMNS = (
    Session.id,
    Session.name,
    Session.map_id,
    Session.source,
    Session.log_name,
    Session.log_sha256,
    Session.topics,
    Session.params,
    Session.code_version,
    Session.status,
    Session.frames_processed,
    Session.frames_total,
    Session.first_stamp,
    Session.last_stamp,
    Session.started_at,
    Session.finished_at,
)


def _record(row: Any) -> SessionRecord:
    return SessionRecord(
        id=int(row[0]),
        name=str(row[1]),
        map_id=None if row[2] is None else int(row[2]),
        source=str(row[3]),
        log_name=str(row[4]),
        log_sha256=str(row[5]),
        topics=dict(row[6]),
        params=dict(row[7]),
        code_version=str(row[8]),
        status=str(row[9]),
        frames_processed=int(row[10]),
        frames_total=None if row[11] is None else int(row[11]),
        first_stamp=row[12],
        last_stamp=row[13],
        started_at=row[14],
        finished_at=row[15],
    )


def topics_key(topics: Mapping[str, Any]) -> str:
    """Return the SHA-256 of the canonical JSON of a topic mapping (part of a session's identity)."""
    canonical = json.dumps(dict(topics), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode("utf-8")).hexdigest()


def find_session(*, conn: Connection, log_sha256: str, topics: Mapping[str, Any]) -> SessionRecord | None:
    """Return the session built from this log with this topic mapping, or None."""
    row = conn.execute(
        select(*_COLUMNS).where(Session.log_sha256 == log_sha256, Session.topics_key == topics_key(topics))
    ).first()
    return None if row is None else _record(row)


def get_session(*, conn: Connection, session_id: int) -> SessionRecord:
    """Return the session with id ``session_id``.

    Raises:
        NotFoundError: no such session.
    """
    row = conn.execute(select(*_COLUMNS).where(Session.id == session_id)).first()
    if row is None:
        msg = f"no session with id {session_id!r}"
        raise NotFoundError(msg)
    return _record(row)


def sessions_of_map(*, conn: Connection, map_id: int) -> list[SessionRecord]:
    """Return the sessions of a map in creation order."""
    rows = conn.execute(select(*_COLUMNS).where(Session.map_id == map_id).order_by(Session.id)).all()
    return [_record(r) for r in rows]


def get_sessions(*, conn: Connection, session_ids: list[int]) -> list[SessionRecord]:
    """Return the sessions with these ids, in the given order.

    Raises:
        NotFoundError: an id names no session.
    """
    rows = conn.execute(select(*_COLUMNS).where(Session.id.in_(session_ids))).all()
    by_id = {int(r[0]): _record(r) for r in rows}
    missing = [i for i in session_ids if i not in by_id]
    if missing:
        msg = f"no session with id(s) {missing!r}"
        raise NotFoundError(msg)
    return [by_id[i] for i in session_ids]


def find_session_map(*, conn: Connection, name: str) -> tuple[str, int | None] | None:
    """Return ``(name, map id)`` of the session called ``name`` (map id None: it belongs to no map), or None."""
    row = conn.execute(select(Session.name, Session.map_id).where(Session.name == name)).first()
    return None if row is None else (str(row[0]), None if row[1] is None else int(row[1]))


def session_names(*, conn: Connection, session_ids: Collection[int]) -> dict[int, str]:
    """Return ``{id: name}`` of the sessions among ``session_ids`` (ids that name no session are left out)."""
    rows = conn.execute(select(Session.id, Session.name).where(Session.id.in_(session_ids))).all()
    return {int(r[0]): str(r[1]) for r in rows}


def unique_session_name(*, conn: Connection, wanted: str) -> str:
    """Return ``wanted`` (trimmed) or ``wanted-2``, ``wanted-3``... whichever no session has yet."""
    base = (wanted.strip() or "session")[: NAME_LIMIT - 8]
    taken = set(
        conn.execute(select(Session.name).where(Session.name.like(f"{_escape_like(base)}%", escape="\\"))).scalars()
    )
    if base not in taken:
        return base
    k = 2
    while f"{base}-{k}" in taken:
        k += 1
    return f"{base}-{k}"


def _escape_like(text: str) -> str:
    return text.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")


def _reckoning_blob(rows: npt.ArrayLike | None) -> bytes | None:
    if rows is None:
        return None
    array = np.ascontiguousarray(rows, dtype="<f8").reshape(-1, 4)
    return array.tobytes()


def create_session(*, conn: Connection, spec: NewSession) -> SessionRecord:
    """Insert a session (not yet in any map; :func:`~mapserver.store.state.write_map_state` attaches it).

    Returns:
        The stored session (its name may carry a suffix, see :func:`unique_session_name`).
    """
    name = unique_session_name(conn=conn, wanted=spec.name)
    now = utcnow()
    values = {
        "name": name,
        "map_id": None,
        "source": spec.source,
        "log_name": spec.log_name[:500],
        "log_sha256": spec.log_sha256,
        "topics": dict(spec.topics),
        "topics_key": topics_key(spec.topics),
        "params": dict(spec.params),
        "code_version": __version__,
        "status": spec.status,
        "frames_processed": int(spec.frames_processed),
        "frames_total": spec.frames_total,
        "first_stamp": spec.first_stamp,
        "last_stamp": spec.last_stamp,
        "reckoning": _reckoning_blob(spec.reckoning),
        "reckoning_pose": None if spec.reckoning_pose is None else [float(v) for v in spec.reckoning_pose],
        "started_at": spec.started_at or now,
        "finished_at": now if spec.status == "complete" else None,
        "updated_at": now,
    }
    session_id = conn.execute(insert(Session).values(**values).returning(Session.id)).scalar_one()
    return get_session(conn=conn, session_id=int(session_id))


def update_session(
    *,
    conn: Connection,
    session_id: int,
    status: str,
    frames_processed: int,
    last_stamp: float | None,
    reckoning: npt.ArrayLike | None = None,
    reckoning_pose: tuple[float, float, float, float] | None = None,
) -> SessionRecord:
    """Record a session's progress after more frames were processed (``process`` resuming it)."""
    values: dict[str, Any] = {
        "status": status,
        "frames_processed": int(frames_processed),
        "last_stamp": last_stamp,
        "updated_at": utcnow(),
    }
    if status == "complete":
        values["finished_at"] = values["updated_at"]
    if reckoning is not None:
        values["reckoning"] = _reckoning_blob(reckoning)
    if reckoning_pose is not None:
        values["reckoning_pose"] = [float(v) for v in reckoning_pose]
    conn.execute(update(Session).where(Session.id == session_id).values(**values))
    return get_session(conn=conn, session_id=session_id)


def get_reckoning(*, conn: Connection, session_id: int) -> tuple[np.ndarray, tuple[float, ...] | None]:
    """Return a session's dead-reckoning rows (N, 4) ``[stamp, x, y, z]`` and its final pose (or None)."""
    row = conn.execute(select(Session.reckoning, Session.reckoning_pose).where(Session.id == session_id)).first()
    if row is None:
        msg = f"no session with id {session_id!r}"
        raise NotFoundError(msg)
    rows = np.zeros((0, 4)) if row[0] is None else np.frombuffer(row[0], dtype="<f8").reshape(-1, 4).astype(float)
    pose = None if row[1] is None else tuple(float(v) for v in row[1])
    return rows, pose


ACTIVATION_COLUMNS = 4
"""``[stamp, template session id, template origin index, created (0/1)]``; template −1/−1 when none."""


def set_activations(*, conn: Connection, session_id: int, rows: npt.ArrayLike) -> None:
    """Store a session's per-frame activations (N, 4), replacing what was stored (see :data:`ACTIVATION_COLUMNS`)."""
    array = np.ascontiguousarray(rows, dtype="<f8").reshape(-1, ACTIVATION_COLUMNS)
    conn.execute(update(Session).where(Session.id == session_id).values(activations=array.tobytes()))


def get_activations(*, conn: Connection, session_id: int) -> np.ndarray | None:
    """Return a session's per-frame activations (N, 4), or None when none were stored (before migration 0005)."""
    blob = conn.execute(select(Session.activations).where(Session.id == session_id)).scalar_one_or_none()
    if blob is None:
        return None
    return np.frombuffer(blob, dtype="<f8").reshape(-1, ACTIVATION_COLUMNS).astype(np.float64)


@dataclass(frozen=True, slots=True)
class SessionProgress:
    """How far a session stands, as stored: what an unmerge changes in its row and a redo puts back exactly.

    ``reckoning`` and ``activations`` are the row's blobs as stored (float64 LE, N × 4; None when absent).
    """

    session_id: int
    status: str
    frames_processed: int
    last_stamp: float | None
    reckoning: bytes | None
    reckoning_pose: list[float] | None
    activations: bytes | None
    finished_at: datetime | None


def get_session_progress(*, conn: Connection, session_id: int) -> SessionProgress:
    """Return a session's progress columns as stored (see :class:`SessionProgress`).

    Raises:
        NotFoundError: no such session.
    """
    row = conn.execute(
        select(Session.status, Session.frames_processed, Session.last_stamp, Session.reckoning,
               Session.reckoning_pose, Session.activations, Session.finished_at).where(Session.id == session_id)
    ).first()  # fmt: skip
    if row is None:
        msg = f"no session with id {session_id!r}"
        raise NotFoundError(msg)
    return SessionProgress(
        session_id=session_id, status=str(row[0]), frames_processed=int(row[1]), last_stamp=row[2],
        reckoning=None if row[3] is None else bytes(row[3]),
        reckoning_pose=None if row[4] is None else [float(v) for v in row[4]],
        activations=None if row[5] is None else bytes(row[5]), finished_at=row[6],
    )  # fmt: skip


def set_session_progress(*, conn: Connection, progress: SessionProgress) -> None:
    """Write a session's progress columns back exactly as :func:`get_session_progress` read them."""
    conn.execute(
        update(Session).where(Session.id == progress.session_id).values(
            status=progress.status, frames_processed=progress.frames_processed, last_stamp=progress.last_stamp,
            reckoning=progress.reckoning, reckoning_pose=progress.reckoning_pose, activations=progress.activations,
            finished_at=progress.finished_at, updated_at=utcnow(),
        )
    )  # fmt: skip


def cut_session(
    *, conn: Connection, session_id: int, frames: int, status: str, last_stamp: float,
    reckoning_pose: tuple[float, float, float, float] | None,
) -> SessionRecord:  # fmt: skip
    """Set a session back to its first ``frames`` frames: progress, dead reckoning and activation timeline cut there.

    ``status`` ``complete``: the session ends there (a whole map of those frames); ``partial``: processing its
    log again continues it from frame ``frames``.
    """
    rows, _pose = get_reckoning(conn=conn, session_id=session_id)
    update_session(
        conn=conn, session_id=session_id, status=status, frames_processed=frames, last_stamp=last_stamp,
        reckoning=rows[:frames], reckoning_pose=reckoning_pose,
    )  # fmt: skip
    activations = get_activations(conn=conn, session_id=session_id)
    if activations is not None:
        set_activations(conn=conn, session_id=session_id, rows=activations[:frames])
    return get_session(conn=conn, session_id=session_id)

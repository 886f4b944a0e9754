"""The one place that runs a mission log through the engine, the store and the merger.

Both faces (``mapserver process`` and the REST API's jobs) call :func:`process_log`, or
:func:`process_into_store` to keep the session in a database.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from core import ConfigError, Engine, ImageError, Params
from core.motion import Motion
from mapserver.errors import InputError
from mapserver.formats import SessionInfo, map_json, write_map_json
from mapserver.ingest import open_log

logger = logging.getLogger(__name__)

ProgressCallback = Callable[[int, int], None]


@dataclass
class ProcessResult:
    """What processing one log produced (the CLI's JSON summary is :meth:`summary`)."""

    frames: int
    templates: int
    experiences: int
    links: int
    loop_closures: int
    map_name: str
    seconds: float
    merges: list[dict[str, Any]] = field(default_factory=list)
    session_id: int | None = None
    engine: Engine | None = None
    document: dict[str, Any] | None = None

    def summary(self) -> dict[str, Any]:
        """Return the contract's ``process --json`` object."""
        return {
            "frames": self.frames,
            "templates": self.templates,
            "experiences": self.experiences,
            "links": self.links,
            "loop_closures": self.loop_closures,
            "merges": self.merges,
            "map": self.map_name,
            "seconds": round(self.seconds, 3),
            "frames_per_s": round(self.frames / self.seconds, 1) if self.seconds > 0 else None,
        }


class DeadReckoning:
    """Integrates the frames' motions into raw odometry positions (for evaluation against ground truth)."""

    def __init__(self, initial_yaw: float) -> None:
        self.pose = np.array([0.0, 0.0, 0.0, initial_yaw])
        self.rows: list[tuple[float, float, float, float]] = []

    def add(self, stamp: float, motion: Motion) -> None:
        """Compose one body-frame motion and record the position at ``stamp``."""
        x, y, z, yaw = self.pose
        c, s = math.cos(yaw), math.sin(yaw)
        self.pose = np.array(
            [x + c * motion.dx - s * motion.dy, y + s * motion.dx + c * motion.dy, z + motion.dz, yaw + motion.dyaw]
        )
        self.rows.append((stamp, float(self.pose[0]), float(self.pose[1]), float(self.pose[2])))

    def array(self) -> np.ndarray:
        """Return the (N, 4) ``[stamp, x, y, z]`` rows."""
        return np.asarray(self.rows, dtype=np.float64).reshape(-1, 4)


def run_engine(
    engine: Engine,
    log_path: str | Path,
    *,
    topics: Mapping[str, str] | None = None,
    start: int = 0,
    stop: int | None = None,
    progress: ProgressCallback | None = None,
    on_step: Callable[[Any, Any], None] | None = None,
) -> tuple[int, DeadReckoning, Any]:
    """Feed frames ``[start, stop)`` of a log through ``engine``; return (frames, dead reckoning, log info).

    ``on_step(frame, result)`` is called after every frame (the merger and the evidence
    collector hook in here).
    """
    # The engine's matrices are small: multi-threaded BLAS only adds contention (2-5x slower on a busy machine).
    with threadpool_limits(limits=1, user_api="blas"), open_log(log_path, topics) as log:
        total = log.count_frames()
        end = total if stop is None else min(stop, total)
        reckoning = DeadReckoning(math.radians(engine.params.exp_initial_em_deg))
        count = 0
        for frame in log.frames(start, end):
            stamp = frame.stamp_ns * 1e-9
            try:
                result = engine.step(frame.image, frame.motion, stamp)
            except ImageError as err:  # images smaller than the preset's template or crop
                msg = f"{log_path}: frame {start + count} cannot be processed with these parameters: {err}"
                raise InputError(msg) from err
            reckoning.add(stamp, result.motion)
            if on_step is not None:
                on_step(frame, result)
            count += 1
            if progress is not None:
                progress(count, end - start)
        info = {"sha256": log.sha256, "mapping": log.mapping.as_dict(), "total_frames": total}
    return count, reckoning, info


def process_log(
    log_path: str | Path,
    params: Params,
    *,
    topics: Mapping[str, str] | None = None,
    out: str | Path | None = None,
    progress: ProgressCallback | None = None,
) -> ProcessResult:
    """Run the engine over one log without a database; optionally write the map JSON to ``out``.

    Raises:
        InputError: the log cannot be read (``IngestError``) or the parameters are invalid.
    """
    started = time.perf_counter()
    name = Path(log_path).name.split(".")[0] or "map"
    try:
        engine = Engine(params, origin=0)
    except ConfigError as err:
        raise InputError(str(err)) from err
    frame_rows: list[tuple[float, int, int]] = []  # the map JSON "frames" extension

    def record(frame: Any, result: Any) -> None:
        frame_rows.append((frame.stamp_ns * 1e-9, int(result.template), int(result.template_created)))

    frames, reckoning, info = run_engine(engine, log_path, topics=topics, progress=progress, on_step=record)
    if frames == 0:
        msg = f"{log_path}: the camera topic has no frames"
        raise InputError(msg)
    engine.settle()
    snapshot = engine.snapshot()
    document = map_json(
        params=params.to_dict(),
        snapshot=snapshot,
        sessions=[SessionInfo(name=name, log_sha256=info["sha256"], frames=frames)],
        session_name_by_origin={0: name},
        odometry=reckoning.array(),
        frames=frame_rows,
    )
    if out is not None:
        write_map_json(out, document)
    src = snapshot["em_link_from"]
    return ProcessResult(
        frames=frames,
        templates=engine.template_count,
        experiences=engine.experience_count,
        links=int(src.shape[0]),
        loop_closures=engine.loop_closures,
        map_name=name,
        seconds=time.perf_counter() - started,
        engine=engine,
        document=document,
    )


# ----------------------------------------------------------------------------------------------- store

NEW_SESSION_ORIGIN = 0
"""Origin tag of a new session's templates and experiences until it has an id (stored ids start at 1)."""


def _log_stem(log_path: str | Path) -> str:
    return Path(log_path).name.split(".")[0] or "map"


def _merge_candidates(db: Any, *, params: Params, session_map_id: int | None, enabled: bool) -> list[Any]:
    """MERGE HOOK (issue 5): the stored maps this session may merge into online.

    Online merging is not implemented here yet: this returns no candidate, so the session always
    becomes (or continues) its own map and ``merges`` is ``[]``. The merger plugs in by returning
    the candidate maps (loaded with ``mapserver.store.read_map_state``), feeding every frame to its
    matcher in ``process_into_store``'s run (swapping the engine when a merge is confirmed), and, in
    the write transaction, recording the event (``store.merge_events.record_merge_event``), archiving
    the pre-merge states (``store.archive.archive_map_state`` / ``archive_state``), dropping maps that
    were joined (``store.drop_map``) and writing the merged state with the renumbered identities.
    """
    del db, params, session_map_id, enabled
    return []


def _existing_result(db: Any, session: Any, map_id: int, started: float, out: str | Path | None) -> ProcessResult:
    """Answer with a stored session (no processing); write ``out`` from the stored map."""
    from sqlalchemy import func, select

    from mapserver.store import load_map
    from mapserver.store.export import map_document
    from mapserver.store.maps import get_map_by_id
    from mapserver.store.models import Link, MapState

    with db.read() as conn:
        record = get_map_by_id(conn=conn, map_id=map_id)
        counts = conn.execute(
            select(MapState.n_templates, MapState.n_experiences, MapState.n_links).where(MapState.map_id == map_id)
        ).first()
        loops = conn.execute(
            select(func.count()).select_from(Link).where(Link.map_id == map_id, Link.kind == "loop")
        ).scalar_one()
    document = None
    if out is not None:
        document = map_document(load_map(db, name=record.name))
        write_map_json(out, document)
    templates, experiences, links = (int(v) for v in counts) if counts is not None else (0, 0, 0)
    return ProcessResult(
        frames=session.frames_processed,
        templates=templates,
        experiences=experiences,
        links=links,
        loop_closures=int(loops),
        map_name=record.name,
        seconds=time.perf_counter() - started,
        session_id=session.id,
        document=document,
    )


def process_into_store(
    log_path: str | Path,
    params: Params,
    *,
    db_url: str | None,
    map_name: str | None = None,
    topics: Mapping[str, str] | None = None,
    merge: bool = True,
    stop_after: int | None = None,
    out: str | Path | None = None,
    progress: ProgressCallback | None = None,
) -> ProcessResult:
    """Run a log through the engine and store the session in a database, in one transaction.

    A log is identified by its SHA-256 and topic mapping. A new log becomes a new session in a new map
    called ``map_name`` (default: the log's name). A log stored partially (``stop_after``) continues from
    its next frame in the same session and map, from the exact stored engine state, so processing
    frames [0, k) then [k, N) gives the same map as [0, N) in one go. A complete log is answered with
    the stored session (a warning says so). The map is relaxed to convergence (``settle``) only when the
    session's last frame has been processed.

    Args:
        log_path: the mission log.
        params: engine parameters (a continued session must use the ones it was stored with).
        db_url: SQLAlchemy URL (None: the default SQLite file); an empty database gets the schema.
        map_name: name of the new map (an error if a map of that name exists and the log is not one of
            its sessions).
        topics: topic overrides.
        merge: try online merging into stored maps (issue 5; see :func:`_merge_candidates`).
        stop_after: stop when the session has processed this many frames in total (resume later).
        out: also write the map JSON here.
        progress: ``progress(done, total)`` callback.

    Returns:
        The summary (``frames`` counts the session's frames so far).

    Raises:
        InputError: unreadable log, no frames, invalid ``stop_after``, a map name taken, or parameters
            that differ from the stored session's.
        ConflictError: another process wrote the same map concurrently twice in a row.
    """
    from mapserver.store import StaleMapError, open_database

    if stop_after is not None and stop_after < 1:
        msg = f"--stop-after must be at least 1, got {stop_after!r}"
        raise InputError(msg)
    started = time.perf_counter()
    with open_log(log_path, topics) as log:
        identity = {"sha256": log.sha256, "mapping": log.mapping.as_dict(), "total": log.count_frames()}
    with open_database(db_url) as db:
        for attempt in (1, 2):
            try:
                return _process_session(
                    db, log_path, params, identity,
                    map_name=map_name, topics=topics, merge=merge, stop_after=stop_after, out=out,
                    progress=progress, started=started,
                )  # fmt: skip
            except StaleMapError as err:
                if attempt == 2:
                    raise
                logger.warning("%s; processing the log again", err)
    raise AssertionError("unreachable")  # pragma: no cover


def _process_session(
    db: Any,
    log_path: str | Path,
    params: Params,
    identity: Mapping[str, Any],
    *,
    map_name: str | None,
    topics: Mapping[str, str] | None,
    merge: bool,
    stop_after: int | None,
    out: str | Path | None,
    progress: ProgressCallback | None,
    started: float,
) -> ProcessResult:
    """One attempt of :func:`process_into_store` (redone once when the map changed meanwhile)."""
    from core import Action, params_from_dict
    from mapserver.store import find_map, find_session, get_map_by_id, read_map_state
    from mapserver.store.evidence import EvidenceCollector, save_evidence
    from mapserver.store.maps import create_map
    from mapserver.store.sessions import NewSession, create_session, get_reckoning, update_session
    from mapserver.store.state import plain_params, write_map_state

    wanted = plain_params(params)
    name = map_name or _log_stem(log_path)
    total = int(identity["total"])
    content = None
    session = None
    with db.read() as conn:
        session = find_session(conn=conn, log_sha256=identity["sha256"], topics=identity["mapping"])
        if session is not None:
            if session.params != wanted:
                keys = sorted(k for k in set(wanted) | set(session.params) if wanted.get(k) != session.params.get(k))
                msg = (
                    f"{str(log_path)!r} is stored already as session {session.name!r} with other parameters "
                    f"({', '.join(keys[:5])}{', ...' if len(keys) > 5 else ''} differ); use the same preset/config"
                )
                raise InputError(msg)
            if session.map_id is None:
                msg = f"session {session.name!r} belongs to no map at the moment (an unmerge in progress?)"
                raise InputError(msg)
            record = get_map_by_id(conn=conn, map_id=session.map_id)
            if map_name is not None and map_name != record.name:
                msg = (
                    f"{str(log_path)!r} is session {session.name!r} of map {record.name!r}; "
                    f"it cannot be stored in map {map_name!r}"
                )
                raise InputError(msg)
            done = session.frames_processed
            if session.complete or (stop_after is not None and done >= stop_after):
                logger.warning(
                    "%s is stored already as session %r of map %r (%d of %d frames): answering with it",
                    log_path, session.name, record.name, done, total,
                )  # fmt: skip
                return _existing_result(db, session, record.id, started, out)
            content = read_map_state(conn=conn, map_id=record.id)
            stored_rows, stored_pose = get_reckoning(conn=conn, session_id=session.id)
        elif find_map(conn=conn, name=name) is not None:
            msg = f"a map named {name!r} already exists and this log is not one of its sessions; choose --map NAME"
            raise InputError(msg)

    if content is not None and session is not None:
        engine = Engine.restore(params_from_dict(content.params), content.snapshot, origin=session.id)
        start = session.frames_processed
        reckoning = DeadReckoning(math.radians(params.exp_initial_em_deg))
        if stored_pose is not None:
            reckoning.pose = np.asarray(stored_pose, dtype=np.float64)
    else:
        try:
            engine = Engine(params, origin=NEW_SESSION_ORIGIN)
        except ConfigError as err:
            raise InputError(str(err)) from err
        start = 0
        stored_rows = np.zeros((0, 4))
        reckoning = DeadReckoning(math.radians(params.exp_initial_em_deg))
    stop = total if stop_after is None else min(stop_after, total)
    candidates = _merge_candidates(  # MERGE HOOK (issue 5)
        db, params=params, session_map_id=None if session is None else session.map_id, enabled=merge
    )
    collector = EvidenceCollector(params.sync_stale_sec)
    stamps: list[float] = []

    def on_step(frame: Any, result: Any) -> None:
        stamp = frame.stamp_ns * 1e-9
        stamps.append(stamp)
        collector.observe(stamp, frame.image)
        if result.action == Action.CREATE_NODE:
            collector.experience(result.experience, stamp)
        reckoning.add(stamp, result.motion)

    frames, _odometry, _info = run_engine(
        engine, log_path, topics=topics, start=start, stop=stop, progress=progress, on_step=on_step
    )
    if frames == 0 and content is None:
        msg = f"{log_path}: the camera topic has no frames"
        raise InputError(msg)
    processed = start + frames
    complete = processed >= total
    if complete:
        engine.settle()
    snapshot = engine.snapshot()
    images = collector.finish()
    rows = np.concatenate([stored_rows, reckoning.array()])
    pose = tuple(float(v) for v in reckoning.pose)
    status = "complete" if complete else "partial"
    del candidates
    with db.write() as conn:
        if content is not None and session is not None:
            map_id = content.meta.map.id
            version = content.meta.map.version
            session_ids = [s.id for s in content.meta.sessions]
            origins = {s: s for s in session_ids}
            session_id = session.id
            update_session(
                conn=conn, session_id=session_id, status=status, frames_processed=processed,
                last_stamp=stamps[-1] if stamps else session.last_stamp, reckoning=rows, reckoning_pose=pose,
            )  # fmt: skip
            template_index, experience_index = content.meta.template_index, content.meta.experience_index
        else:
            record = create_map(conn=conn, name=name, params=wanted)
            map_id, version = record.id, record.version
            created = create_session(
                conn=conn,
                spec=NewSession(
                    name=_log_stem(log_path),
                    log_name=Path(log_path).name,
                    log_sha256=identity["sha256"],
                    topics=identity["mapping"],
                    params=wanted,
                    status=status,
                    frames_processed=processed,
                    frames_total=total,
                    first_stamp=stamps[0] if stamps else None,
                    last_stamp=stamps[-1] if stamps else None,
                    origin=NEW_SESSION_ORIGIN,
                    reckoning=rows,
                    reckoning_pose=pose,  # type: ignore[arg-type]
                ),
            )
            session_id = created.id
            session_ids = [session_id]
            origins = {NEW_SESSION_ORIGIN: session_id}
            template_index = experience_index = None
        written = write_map_state(
            conn=conn, map_id=map_id, expected_version=version, params=engine.params, snapshot=snapshot,
            session_ids=session_ids, origins=origins, template_index=template_index,
            experience_index=experience_index,
        )  # fmt: skip
        mine = written.experience_session == session_id
        items = [(int(written.experience_index[img.experience]), img) for img in images if mine[img.experience]]
        save_evidence(conn=conn, session_id=session_id, items=items)
        map_record = get_map_by_id(conn=conn, map_id=map_id)
        sessions_now = _sessions(conn, session_ids)
    names = {s.id: s.name for s in sessions_now}
    document = None
    if out is not None:
        stored_snapshot = {**snapshot, "lv_origin": written.template_session, "em_origin": written.experience_session}
        document = map_json(
            params=plain_params(engine.params),
            snapshot=stored_snapshot,
            sessions=[SessionInfo(s.name, s.log_sha256, s.frames_processed) for s in sessions_now],
            session_name_by_origin=names,
            odometry=rows if len(sessions_now) == 1 else None,
        )
        write_map_json(out, document)
    return ProcessResult(
        frames=processed,
        templates=engine.template_count,
        experiences=engine.experience_count,
        links=int(snapshot["em_link_from"].shape[0]),
        loop_closures=engine.loop_closures,
        map_name=map_record.name,
        seconds=time.perf_counter() - started,
        session_id=session_id,
        engine=engine,
        document=document,
    )


def _sessions(conn: Any, session_ids: list[int]) -> list[Any]:
    from mapserver.store.sessions import get_sessions

    return get_sessions(conn=conn, session_ids=session_ids)

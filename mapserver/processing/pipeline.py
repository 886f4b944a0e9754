"""The one place that runs a mission log through the engine, the store and the merger.

Both faces (``mapserver process`` and the REST API's jobs) call :func:`process_log` (from
:mod:`mapserver.processing.run`), or :func:`process_into_store` to keep the session in a database.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from core import ConfigError, Engine, Params
from mapserver.errors import InputError
from mapserver.formats import SessionInfo, map_json, write_map_json
from mapserver.ingest import LogIdentity, MissionLog, open_log
from mapserver.names import check_map_name, default_map_name, log_stem
from mapserver.processing.reckoning import DeadReckoning
from mapserver.processing.run import (  # re-exported: the pipeline is where callers find them
    EngineRun,
    ProcessResult,
    ProgressCallback,
    StepHook,
    load_frontend,
    process_log,
    run_engine,
)
from mapserver.statuses import MergeStatus
from mapserver.store import Database, utcnow

if TYPE_CHECKING:
    from mapserver.atlas import AtlasMap
    from mapserver.ingest.frames import IngestReport
    from mapserver.merge import OnlineMerger
    from mapserver.merge.identity import RowIdentities
    from mapserver.merge.resume import MergerState
    from mapserver.processing.live import PendingMerge
    from mapserver.store import Connection, Database, SessionRecord
    from mapserver.store.evidence import EvidenceCollector

logger = logging.getLogger(__name__)

STALE_ATTEMPTS = 3
"""Runs of one log before giving up when concurrent writers keep changing the maps it merges with."""

# ----------------------------------------------------------------------------------------------- store

NEW_SESSION_ORIGIN = 0
"""Origin tag of a new session's templates and experiences until it has an id (stored ids start at 1).

The engine stamps rows with its origin tag (``Engine(params, origin=tag)``); a resumed session's engine
runs with its session id. The store maps tag 0 to the new session's id when it saves (``origins``).
"""


def _existing_result(
    db: Database, session: SessionRecord, map_id: int, started: float, out: str | Path | None
) -> ProcessResult:
    """Answer with a stored session (no processing); write ``out`` from the stored map."""
    from mapserver.store import load_map
    from mapserver.store.export import map_document
    from mapserver.store.maps import get_map_by_id
    from mapserver.store.queries import count_links, map_state_counts

    with db.read() as conn:
        record = get_map_by_id(conn=conn, map_id=map_id)
        counts = map_state_counts(conn=conn, map_id=map_id)
        loops = count_links(conn=conn, map_id=map_id, kind="loop")
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
    db: Database | None = None,
    identity: LogIdentity | None = None,
    map_name: str | None = None,
    topics: Mapping[str, str] | None = None,
    merge: bool = True,
    stop_after: int | None = None,
    out: str | Path | None = None,
    progress: ProgressCallback | None = None,
    confirm: int | None = None,
    shift_lattice: bool = True,
    into: str | None = None,
) -> ProcessResult:
    """Run a log through the engine and store the session in a database, in one transaction.

    A log is identified by its SHA-256 and topic mapping. A new log becomes a new session. With
    ``merge`` (the default) every frame is matched against the stored maps of the atlas that can
    merge with it (:func:`mapserver.atlas.merge_candidates`); a confirmed match merges the session
    into that map online and mapping continues in the merged map; the session may merge again into
    another map (a session bridging two maps joins them). A session that connects to no map becomes a
    new map called ``map_name`` (default: the log's name, :func:`mapserver.names.default_map_name`). A log
    stored partially (``stop_after``) continues from its next frame in the same session and map, from the
    exact stored engine state (and merge driver state), so processing frames [0, k) then [k, N) gives the
    same map as [0, N) in one go.
    A complete log is answered with the stored session (a warning says so). The map is relaxed to
    convergence (``settle``) only when the session's last frame has been processed.

    Args:
        log_path: the mission log.
        params: engine parameters (a continued session must use the ones it was stored with).
        db_url: SQLAlchemy URL (None: the default SQLite file); an empty database gets the schema. Opened
            here, unless ``db`` is given.
        db: the process's open database (the server's or a worker's), used instead of opening ``db_url``.
        identity: the log's identity read when it was first opened (the upload's check); None reads it
            here (hashing the log).
        map_name: name of the new map when the session connects to none (an error if it breaks the map
            name rule, :func:`mapserver.names.check_map_name`, or a map of that name exists and the log is
            not one of its sessions).
        topics: topic overrides.
        merge: merge online into the stored maps the session connects to; False keeps it a separate map.
        stop_after: stop when the session has processed this many frames in total (resume later); a merge
            on probation then is verified first (the session stops when its probation concludes).
        out: also write the map JSON here.
        progress: ``progress(done, total)`` callback.
        confirm: K, consecutive matching frames that confirm a merge (None: ``params.merge_confirm``).
        shift_lattice: False disables merge operation (iii), the lattice shift (debug, Fig. 12).
        into: merge into this stored map only: the map alone is the merge candidate, and a session that
            does not end up merged into it (no confirmed merge, or one its verification rolled back) is
            refused with nothing stored. Excludes ``map_name`` and ``stop_after``; needs ``merge``.

    Returns:
        The summary (``frames`` counts the session's frames so far; ``merges`` one entry per merge).

    Raises:
        InputError: unreadable log, no frames, invalid ``stop_after`` or ``confirm``, a map name taken, or
            parameters that differ from the stored session's.
        ConflictError: concurrent writers changed the maps this session reads or may merge into during
            each of ``STALE_ATTEMPTS`` runs.
    """
    from mapserver.processing.live import LiveSession  # noqa: F401  (with the store: loaded before the clock starts)
    from mapserver.store import StaleMapError
    from mapserver.store.db import commit_gate
    from mapserver.store.evidence import EvidenceCollector  # noqa: F401

    if stop_after is not None and stop_after < 1:
        msg = f"--stop-after must be at least 1, got {stop_after!r}"
        raise InputError(msg)
    if confirm is not None and confirm < 1:
        msg = f"--confirm must be at least 1, got {confirm!r}"
        raise InputError(msg)
    if map_name is not None:
        check_map_name(map_name)
    _check_into(into, map_name=map_name, merge=merge, stop_after=stop_after)
    load_frontend(params)
    started = time.perf_counter()
    options = _Options(map_name, merge, stop_after, out, progress, started, confirm, shift_lattice, utcnow(), into)
    with open_log(log_path, topics) as log, _database(db, db_url) as store:
        known = LogIdentity.of(log) if identity is None else identity
        for attempt in range(1, STALE_ATTEMPTS + 1):
            try:
                if attempt < STALE_ATTEMPTS:
                    return _process_session(store, log_path, log, params, known, options)
                with commit_gate(store):  # the last try: no session of this process commits meanwhile
                    return _process_session(store, log_path, log, params, known, options)
            except StaleMapError as err:
                if attempt == STALE_ATTEMPTS:
                    raise
                logger.warning("%s; processing the log again", err)
    raise AssertionError("unreachable")  # pragma: no cover


@contextlib.contextmanager
def _database(db: Database | None, db_url: str | None) -> Iterator[Database]:
    """Yield ``db`` as it is (its owner closes it), or the database at ``db_url``, opened and closed here."""
    if db is not None:
        yield db
        return
    from mapserver.store import open_database

    with open_database(db_url) as opened:
        yield opened


@dataclass(frozen=True)
class _Options:
    map_name: str | None
    merge: bool
    stop_after: int | None
    out: str | Path | None
    progress: ProgressCallback | None
    started: float
    confirm: int | None
    shift_lattice: bool
    started_at: datetime  # wall-clock time the processing began (the new session's ``started_at``)
    into: str | None = None  # the one map the session must merge into


def _check_into(into: str | None, *, map_name: str | None, merge: bool, stop_after: int | None) -> None:
    """Refuse a target map that the other options contradict (worded for the CLI and the REST API alike)."""
    if into is None:
        return
    check_map_name(into)
    if map_name is not None:
        msg = f"a new map's name ({map_name!r}) and a map to merge into ({into!r}) exclude each other; give one"
        raise InputError(msg)
    if not merge:
        msg = f"merging into map {into!r} needs merging on"
        raise InputError(msg)
    if stop_after is not None:
        msg = f"a session merged into map {into!r} is processed to its end; it cannot stop after {stop_after} frames"
        raise InputError(msg)


def _require_merged_into(into: str | None, holder_id: int | None, candidates: list[Any]) -> None:
    """Refuse to store a session sent into a map when it did not end up merged into that map."""
    if into is None or (holder_id is not None and any(c.id == holder_id for c in candidates)):
        return
    msg = (
        f"the session did not merge into map {into!r}: its views never confirmed a merge with the map, or the "
        "merge was rolled back by its verification; nothing was stored (send it without a map to merge into to "
        "keep it as a map of its own)"
    )
    raise InputError(msg)


def _process_session(
    db: Database, log_path: str | Path, log: MissionLog, params: Params, identity: LogIdentity, opts: _Options
) -> ProcessResult:
    """One attempt of :func:`process_into_store`: read the atlas, run the log, store (redone when stale)."""
    from mapserver.merge import OnlineMerger
    from mapserver.merge.relevance import ViewLog
    from mapserver.processing.live import Holder, LiveSession
    from mapserver.store.evidence import EvidenceCollector

    name = opts.map_name or default_map_name(log_path)
    total = identity.frames
    read = _read_atlas(db, log_path, params, identity, opts, name)
    if isinstance(read, ProcessResult):
        return read
    session, own, candidates = read.session, read.own, read.candidates
    engine, ids, tag, start, reckoning, resume = _start_engine(params, read)
    stop = total if opts.stop_after is None else min(opts.stop_after, total)
    merger = (
        OnlineMerger([c.stored() for c in candidates], confirm=opts.confirm, shift_lattice=opts.shift_lattice,
                     resume=resume)
        if candidates else None
    )  # fmt: skip
    holder = Holder(
        id=None if own is None else own.id, name=name if own is None else own.name,
        sessions=[] if own is None else [s for s in own.session_ids if s != tag], engine=engine, ids=ids,
    )  # fmt: skip
    live = LiveSession(
        holder=holder, tag=tag, start=start, merger=merger, targets={c.id: c for c in candidates},
        collector=EvidenceCollector(params.sync_stale_sec), reckoning=reckoning,
        views=ViewLog(complete=start == 0) if opts.merge else None,
    )  # fmt: skip
    on_probation = None if merger is None or opts.stop_after is None else lambda: merger.probation is not None
    run = run_engine(engine, log, start=start, stop=stop, progress=opts.progress, on_step=live.on_step,
                     overrun=on_probation, identity=identity, reckoning=reckoning)  # fmt: skip
    if run.frames == 0 and own is None:
        msg = f"{log_path}: the camera topic has no frames"
        raise InputError(msg)
    engine = live.finish() or run.engine  # a probation the log ended is judged: its rollback's engine goes on
    if own is None:
        _require_merged_into(opts.into, live.holder.id, candidates)
    ids = live.holder.ids
    if merger is not None:
        for other, reason in merger.skipped.items():
            logger.warning("map %r is not a merge candidate: %s", other, reason)
    processed = start + run.frames
    complete = processed >= total
    if complete:
        engine.settle()
    truth = log_ground_truth_rows(log) if complete else None
    ids.extend(engine.template_count, engine.experience_count, tag)
    progress = _Progress(processed, total, live.stamps, np.concatenate([read.rows, reckoning.array()]),
                         tuple(float(v) for v in reckoning.pose))  # fmt: skip
    return _store_session(db, log_path, params, identity, opts, _RunOutcome(
        session=session, own=own, name=name, engine=engine, ids=ids, pending=live.pending,
        merger=merger if not complete else None, candidates=candidates, progress=progress, collector=live.collector,
        frames_run=run.frames, activations=(read.activations, live.activation_rows),
        relevance=(set() if merger is None else merger.observed, live.views), dropped=run.dropped,
        ground_truth=truth,
    ))  # fmt: skip


def log_ground_truth_rows(log: MissionLog) -> np.ndarray | None:
    """Return the log's ground-truth topic as rows ``[stamp s, x, y, z, qx, qy, qz, qw]`` (None: it has none).

    A ground-truth message that cannot be read leaves the session without ground truth (a warning says so):
    the map does not depend on it.
    """
    try:
        rows = [(s.stamp_ns * 1e-9, s.x, s.y, s.z, s.qx, s.qy, s.qz, s.qw) for s in log.ground_truth()]
    except InputError as err:
        logger.warning("the log's ground truth is not kept: %s", err)
        return None
    array = np.array(rows, dtype=np.float64).reshape(-1, 8)
    if array.shape[0] == 0 or not np.isfinite(array).all():
        return None
    return array


@dataclass
class _AtlasRead:
    """What a run starts from: the session stored already (resumed) and its map, and the merge candidates."""

    session: SessionRecord | None = None
    own: AtlasMap | None = None  # the resumed session's map
    rows: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # stored dead reckoning
    pose: tuple[float, ...] | None = None  # its final pose
    activations: np.ndarray | None = field(default_factory=lambda: np.zeros((0, 4)))  # None: stored before 0005
    candidates: list[AtlasMap] = field(default_factory=list)


def _read_atlas(
    db: Database, log_path: str | Path, params: Params, identity: LogIdentity, opts: _Options, name: str
) -> _AtlasRead | ProcessResult:
    """Read the stored session of this log (if any), its map and the merge candidates, in one read.

    Returns the stored session's summary instead when it is complete (or has the frames asked for).

    Raises:
        InputError: the log is stored with other parameters, its session is in no map or in another map
            than ``--map``, or a map of that name holds other sessions.
    """
    from mapserver import atlas
    from mapserver.store import find_map, find_session, get_map_by_id
    from mapserver.store.sessions import get_activations, get_reckoning

    read = _AtlasRead()
    with db.read() as conn:
        session = find_session(conn=conn, log_sha256=identity.sha256, topics=identity.mapping)
        if session is not None:
            record = get_map_by_id(conn=conn, map_id=_check_stored_session(log_path, params, session))
            if record.archived_at is not None:
                msg = (
                    f"this log is session {session.name!r} of map {record.name!r}, which is archived (deleted); "
                    "restore the map first"
                )
                raise InputError(msg)
            wanted = opts.map_name if opts.into is None else opts.into
            if wanted is not None and wanted != record.name:
                msg = (
                    f"{str(log_path)!r} is session {session.name!r} of map {record.name!r}; "
                    f"it cannot be stored in map {wanted!r}"
                )
                raise InputError(msg)
            done, total = session.frames_processed, identity.frames
            if session.complete or (opts.stop_after is not None and done >= opts.stop_after):
                logger.warning(
                    "%s is stored already as session %r of map %r (%d of %d frames): answering with it",
                    log_path, session.name, record.name, done, total,
                )  # fmt: skip
                return _existing_result(db, session, record.id, opts.started, opts.out)
            read.session, read.own = session, atlas.read_atlas_map(conn, record.id)
            read.rows, read.pose = get_reckoning(conn=conn, session_id=session.id)
            read.activations = get_activations(conn=conn, session_id=session.id)
        elif opts.into is None and (holder := find_map(conn=conn, name=name, archived=None)) is not None:
            msg = (
                f"a map named {name!r} already exists and this log is not one of its sessions; "
                "choose another map name"
                if holder.archived_at is None
                else f"the name {name!r} is held by an archived (deleted) map; restore or purge it, or choose "
                "another map name"
            )
            raise InputError(msg)
        if opts.merge:
            exclude = None if read.own is None else read.own.id
            read.candidates, skipped = atlas.merge_candidates(conn, params=params, exclude=exclude, only=opts.into)
            for other, reason in skipped.items():
                logger.warning("map %r is not a merge candidate: %s", other, reason)
            if opts.into is not None and read.own is None and not read.candidates:
                reason = skipped.get(opts.into) or "there is no live map of that name"
                msg = f"map {opts.into!r} cannot take this session: {reason}"
                raise InputError(msg)
    return read


def _check_stored_session(log_path: str | Path, params: Params, session: SessionRecord) -> int:
    """Check that a stored session can be continued with ``params``; return its map's id.

    A parameter the stored session does not name (it was stored before the parameter existed) takes its
    default: such a session continues with the defaults it was in effect run with.
    """
    from core import params_from_dict
    from mapserver.store.state import plain_params

    wanted = plain_params(params)
    stored = dict(session.params)
    with contextlib.suppress(ConfigError):  # a key this version does not know: compared as stored, and named
        stored = plain_params(params_from_dict(stored))
    if stored != wanted:
        keys = sorted(k for k in set(wanted) | set(stored) if wanted.get(k) != stored.get(k))
        msg = (
            f"{str(log_path)!r} is stored already as session {session.name!r} with other parameters "
            f"({', '.join(keys[:5])}{', ...' if len(keys) > 5 else ''} differ); use the same preset/config"
        )
        raise InputError(msg)
    if session.map_id is None:
        msg = f"session {session.name!r} belongs to no map at the moment (an unmerge in progress?)"
        raise InputError(msg)
    return int(session.map_id)


def _start_engine(
    params: Params, read: _AtlasRead
) -> tuple[Engine, RowIdentities, int, int, DeadReckoning, MergerState | None]:
    """Return (engine, row identities, origin tag, first frame, dead reckoning, merge driver state) to run from.

    A resumed session continues its map's stored engine from its next frame; a new one starts empty.
    """
    from mapserver.merge.identity import RowIdentities
    from mapserver.merge.resume import resume_merger_state

    reckoning = DeadReckoning(math.radians(params.exp_initial_em_deg))
    own, session = read.own, read.session
    if own is not None and session is not None:
        if read.pose is not None:
            reckoning.pose = np.asarray(read.pose, dtype=np.float64)
        engine = Engine.restore(own.params, own.snapshot, origin=session.id)
        resume = resume_merger_state(own, session.id, read.candidates)
        return engine, own.identities.copy(), session.id, session.frames_processed, reckoning, resume
    engine = Engine(params, origin=NEW_SESSION_ORIGIN)  # an invalid front-end setting raises ConfigError
    return engine, RowIdentities(), NEW_SESSION_ORIGIN, 0, reckoning, None


@dataclass(frozen=True)
class _RunOutcome:
    """What a run of the log leaves to store: the session and map it ran in, its engine, merges and records."""

    session: SessionRecord | None  # the stored session it continued (None: a new session)
    own: AtlasMap | None  # that session's map
    name: str  # the new map's name when the session joined none
    engine: Engine
    ids: RowIdentities  # row identities
    pending: list[PendingMerge]  # its merges, applied or rejected
    merger: OnlineMerger | None  # the online merger whose state a resume needs (None: none, or the session is complete)
    candidates: list[AtlasMap]  # the maps it was matched against
    progress: _Progress
    collector: EvidenceCollector  # the evidence collector
    frames_run: int
    activations: tuple[np.ndarray | None, Callable[[dict[int, int]], np.ndarray]]
    """The stored timeline (None: stored before it existed), and the live rows (``LiveSession.activation_rows``)."""
    relevance: tuple[set[object], Any]  # the maps the merger observed, the session's views
    dropped: IngestReport | None = None  # what reading the log dropped
    ground_truth: np.ndarray | None = None  # the log's ground-truth rows, kept with the session once it is complete


def _store_session(
    db: Database, log_path: str | Path, params: Params, identity: LogIdentity, opts: _Options, run: _RunOutcome
) -> ProcessResult:
    """Write the session, its map (merged or not), its merge events and evidence in one transaction.

    The steps: check that the candidate maps did not change (else :class:`StaleMapError`), write the
    session row (:func:`_write_session_row`), claim the maps and the host (:func:`_claim_host`), write the
    merged map with its merge events (applied and rejected), the session's evidence; then answer
    (:func:`_answer`).
    """
    from mapserver import atlas
    from mapserver.merge.resume import merger_keys
    from mapserver.store import evidence as evidence_store
    from mapserver.store import get_map_by_id, lock_atlas
    from mapserver.store.db import commit_gate
    from mapserver.store.sessions import get_sessions

    snapshot = run.engine.snapshot()
    images = run.collector.finish()
    progress = run.progress
    with commit_gate(db), db.write() as conn:
        if opts.merge:
            lock_atlas(conn=conn)
            complete = progress.processed >= progress.total
            atlas.ensure_candidates_unchanged(
                conn, params=params, exclude=None if run.own is None else run.own.id,
                seen={c.id: c.version for c in run.candidates},
                relevance=run.relevance if run.relevance[1] is not None and complete else None, only=opts.into,
            )  # fmt: skip
        session_id = _write_session_row(conn, log_path, params, identity, run, opts.started_at)
        tags = {NEW_SESSION_ORIGIN: session_id} if run.session is None else {}
        claimed, host_id, session_ids = _claim_host(conn, session_id, run, params)
        extra: dict[str, np.ndarray] = {}
        if run.merger is not None:  # the state a resume needs, for the version this write gives the map
            extra = merger_keys(run.merger.export_state(), session_id=session_id, map_version=claimed[host_id] + 1,
                                candidates=run.candidates)  # fmt: skip
        applied, rejected = _merges_to_write(conn, run, session_id, params, session_ids)
        written = atlas.write_merges(
            conn, merges=applied, claimed=claimed, host_id=host_id, params=run.engine.params, snapshot=snapshot,
            identities=run.ids, tags=tags, session_ids=session_ids, extra=extra,
        )  # fmt: skip
        rejected_ids = atlas.write_rejected_merges(conn, merges=rejected, tags=tags)
        e_session, e_index = run.ids.retagged(tags).experience_arrays()
        mine = set(e_index[e_session == session_id].tolist())
        items = [(img.experience, img) for img in images if img.experience in mine]
        evidence_store.save_evidence(conn=conn, session_id=session_id, items=items)
        map_record = get_map_by_id(conn=conn, map_id=host_id)
        sessions_now = get_sessions(conn=conn, session_ids=list(session_ids))
    merges = [atlas.merge_summary(e, w, w.host_name) for e, w in zip(written.event_ids, applied, strict=True)]
    merges += [atlas.merge_summary(e, w, w.host_name) for e, w in zip(rejected_ids, rejected, strict=True)]
    return _answer(opts, run, snapshot, written.result, sessions_now, merges, session_id, map_record.name)


def _merges_to_write(
    conn: Connection, run: _RunOutcome, session_id: int, params: Params, session_ids: list[int]
) -> tuple[list[Any], list[Any]]:
    """Return the session's applied and rejected merges as the store writes them (with every session's frames)."""
    from mapserver.processing.live import merge_to_write
    from mapserver.store.sessions import get_sessions

    frames_now = {s.id: s.frames_processed for s in get_sessions(conn=conn, session_ids=session_ids)}
    writes = [merge_to_write(m, run.pending, session_id, params, frames_now) for m in run.pending]
    pairs = list(zip(writes, run.pending, strict=True))
    applied = [w for w, m in pairs if m.status == MergeStatus.APPLIED]
    return applied, [w for w, m in pairs if m.status == MergeStatus.REJECTED]


@dataclass(frozen=True)
class _Progress:
    """Where the session stands after this run: frames, stamps, dead-reckoning rows and final pose."""

    processed: int
    total: int
    stamps: list[float]
    rows: np.ndarray
    pose: tuple[float, ...]

    @property
    def status(self) -> str:
        """``complete`` once the last frame is processed, else ``partial``."""
        return "complete" if self.processed >= self.total else "partial"


def _write_session_row(
    conn: Connection, log_path: str | Path, params: Params, identity: LogIdentity, run: _RunOutcome,
    started_at: datetime,
) -> int:
    """Create the session's row (or update a resumed one) with its dead reckoning and timeline; return its id."""
    from mapserver.store.sessions import NewSession, create_session, set_activations, update_session
    from mapserver.store.state import plain_params

    session, progress, stamps = run.session, run.progress, run.progress.stamps
    if session is not None:
        session_id = int(session.id)
        update_session(
            conn=conn, session_id=session_id, status=progress.status, frames_processed=progress.processed,
            last_stamp=stamps[-1] if stamps else session.last_stamp, reckoning=progress.rows,
            reckoning_pose=progress.pose,  # type: ignore[arg-type]
        )  # fmt: skip
    else:
        created = create_session(
            conn=conn,
            spec=NewSession(
                name=log_stem(log_path), log_name=Path(log_path).name, log_sha256=identity.sha256,
                topics=identity.mapping, params=plain_params(params), status=progress.status,
                frames_processed=progress.processed, frames_total=progress.total,
                first_stamp=stamps[0] if stamps else None, last_stamp=stamps[-1] if stamps else None,
                origin=NEW_SESSION_ORIGIN, reckoning=progress.rows, reckoning_pose=progress.pose,  # type: ignore[arg-type]
                started_at=started_at,
            ),
        )  # fmt: skip
        session_id = int(created.id)
    if run.ground_truth is not None:
        from mapserver.store.ground_truth import set_ground_truth

        set_ground_truth(conn=conn, session_id=session_id, rows=run.ground_truth)
    stored, live = run.activations
    if stored is not None:
        set_activations(conn=conn, session_id=session_id,
                        rows=np.concatenate([stored, live({NEW_SESSION_ORIGIN: session_id})]))  # fmt: skip
    return session_id


def _claim_host(
    conn: Connection, session_id: int, run: _RunOutcome, params: Params
) -> tuple[dict[int, int], int, list[int]]:
    """Return the maps this write claims (id → version read), the host map and the map's sessions.

    The host is the oldest map involved; a new map (named ``name``) when the session joined none.
    """
    from mapserver.store.maps import create_map
    from mapserver.store.state import plain_params

    own = run.own
    claimed: dict[int, int] = {} if own is None else {own.id: own.version}
    applied = [m for m in run.pending if m.status == MergeStatus.APPLIED]
    claimed.update({m.target.id: m.target.version for m in applied})
    if claimed:
        host_id = min(claimed)
    else:
        host_id = create_map(conn=conn, name=run.name, params=plain_params(params)).id
        claimed = {host_id: 0}
    session_ids = sorted({session_id, *(own.session_ids if own is not None else [])}
                         | {s for m in applied for s in m.target.session_ids})  # fmt: skip
    return claimed, host_id, session_ids


def _answer(
    opts: _Options, run: _RunOutcome, snapshot: Mapping[str, np.ndarray], result: Any, sessions_now: list[Any],
    merges: list[dict[str, Any]], session_id: int, map_name: str,
) -> ProcessResult:  # fmt: skip
    """Log the merges, write the map JSON when asked (``--out``) and return the summary."""
    from mapserver.store.state import plain_params

    engine, progress = run.engine, run.progress
    for entry in merges:
        logger.info("merged into map %r at frame %s (event %d)", entry["into"], entry["frame"], entry["event"])
    document = None
    if opts.out is not None:
        stored_snapshot = {**snapshot, "lv_origin": result.template_session, "em_origin": result.experience_session}
        document = map_json(
            params=plain_params(engine.params),
            snapshot=stored_snapshot,
            sessions=[SessionInfo(s.name, s.log_sha256, s.frames_processed) for s in sessions_now],
            session_name_by_origin={s.id: s.name for s in sessions_now},
            odometry=progress.rows if len(sessions_now) == 1 else None,
        )
        write_map_json(opts.out, document)
    return ProcessResult(
        frames=progress.processed, templates=engine.template_count, experiences=engine.experience_count,
        links=int(snapshot["em_link_from"].shape[0]), loop_closures=engine.loop_closures, map_name=map_name,
        seconds=time.perf_counter() - opts.started, merges=merges, session_id=session_id, engine=engine,
        document=document, frames_run=run.frames_run, dropped=run.dropped,
    )  # fmt: skip


__all__ = [
    "NEW_SESSION_ORIGIN",
    "STALE_ATTEMPTS",
    "EngineRun",
    "ProcessResult",
    "ProgressCallback",
    "StepHook",
    "process_into_store",
    "process_log",
    "run_engine",
]

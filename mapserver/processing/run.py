"""Running a mission log through the engine alone: frames in, the map out (no store, no merging).

:func:`run_engine` feeds a log's frames to an engine (the per-frame hook is where the pipeline books a
live session); :func:`process_log` is ``mapserver process`` without ``--db``. :mod:`mapserver.processing.pipeline`
re-exports both.

Importing this module loads the log reader but not the engine (scipy and the rest load on first use):
:func:`process_log` opens the log and starts reading ahead first, so the reader's child process reads while
the engine's libraries load.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from threadpoolctl import threadpool_limits

from core.config import Params
from mapserver.errors import InputError
from mapserver.formats import SessionInfo, map_json, write_map_json
from mapserver.ingest import Frame, LogIdentity, MissionLog, open_log
from mapserver.ingest.frames import IngestReport
from mapserver.names import log_stem
from mapserver.processing.reckoning import DeadReckoning

if TYPE_CHECKING:
    from core.engine import Engine, StepResult

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
    frames_run: int | None = None
    dropped: IngestReport | None = None

    def summary(self) -> dict[str, Any]:
        """Return the contract's ``process --json`` object.

        ``frames`` counts the session's frames so far; ``frames_per_s`` is this run's rate (frames run
        now, a resumed session's earlier frames not counted); ``dropped`` what this run's reading of the log
        dropped (:meth:`IngestReport.as_dict`).
        """
        run = self.frames if self.frames_run is None else self.frames_run
        return {
            "frames": self.frames,
            "templates": self.templates,
            "experiences": self.experiences,
            "links": self.links,
            "loop_closures": self.loop_closures,
            "merges": self.merges,
            "map": self.map_name,
            "seconds": round(self.seconds, 3),
            "frames_per_s": round(run / self.seconds, 1) if self.seconds > 0 else None,
            "dropped": (self.dropped or IngestReport()).as_dict(),
        }


def view_cells_class(params: Params) -> type:
    """Return the view module of ``params``, loading its libraries (:func:`core.engine.view_cells_class`)."""
    from core.engine import view_cells_class as view_module

    return view_module(params)


def load_frontend(params: Params, frames: int | None = None) -> None:
    """Load what a run of ``frames`` frames will use before its clock starts (torch; the compiled kernels).

    ``sdr-htm`` runs on torch, ``lvc`` on the template matcher's compiled kernel; the pose cells on theirs
    (``core.posecells.COMPILED_AFTER``). The other libraries load when the program starts; these load on first use:
    torch ~2 s here, which counted in ``seconds`` made a 306-frame ``cave3d`` session of ``process --db`` read 70
    frames/s (97–109 with the libraries loaded first), and numba with the kernels' cached machine code ~0.45 s
    (a 266-frame ``twin-overlap`` session: ~15 % of its seconds). A log of ``frames`` frames (None: unknown) too
    short to repay numba's import (:func:`core.posecells.worth_compiling`: one frame, a start-up of well under a
    second) loads no kernel; if its matcher meets a large comparison it loads the kernel then (the answers are the
    same).
    """
    from core._posecell_kernel import load_compiled as load_posecell_kernels
    from core.localview import load_compiled
    from core.posecells import worth_compiling

    view_cells_class(params)
    if frames is not None and not worth_compiling(params.lattice_shape, frames):
        return
    if params.frontend == "lvc":
        load_compiled()
    load_posecell_kernels()


@dataclass
class EngineRun:
    """What :func:`run_engine` did: the engine the log ended in, frames run, dead reckoning, log identity.

    ``dropped``: what reading the log dropped (:class:`~mapserver.ingest.frames.IngestReport`).
    """

    engine: Engine
    frames: int
    reckoning: DeadReckoning
    identity: LogIdentity
    dropped: IngestReport


StepHook = Callable[[Frame, "StepResult"], "Engine | None"]
"""``on_step(frame, result)``: called after every frame; returning an engine continues in it (a merge)."""


def run_engine(
    engine: Engine,
    log: str | Path | MissionLog,
    *,
    topics: Mapping[str, str] | None = None,
    start: int = 0,
    stop: int | None = None,
    progress: ProgressCallback | None = None,
    on_step: StepHook | None = None,
    overrun: Callable[[], bool] | None = None,
    frames: Iterable[Frame] | None = None,
    identity: LogIdentity | None = None,
    reckoning: DeadReckoning | None = None,
) -> EngineRun:
    """Feed frames ``[start, stop)`` of a log through ``engine`` and return the run.

    ``overrun()``, when given, is asked at ``stop`` and after every later frame: while it answers True the run
    goes on past ``stop`` (to the log's end at most) — a session stopped during a merge's probation runs on
    until the probation concludes, so that no stored merge is left unverified.

    ``log`` is a path (opened here) or a log opened by the caller. ``identity``: the log's identity read when
    it was first opened (None: read here, hashing the log). ``reckoning``: the session's dead reckoning to go
    on with (None: a new one from the preset's initial heading); each frame's motion is integrated into it
    here, once, before ``on_step`` (whoever books the frame reads the pose from it).
    ``on_step(frame, result)`` is called after every frame (the merger and the evidence collector hook in
    here); when it returns an engine, the next frames go to that one (an online merge replaced the map the
    session maps in).

    The frames are read and decoded ahead by a worker (:class:`~mapserver.ingest.reader.ReadAhead`) while the
    engine steps, in the same order; ``frames``, when given, are the log's frames from ``start`` on, already
    being read by the caller (who started its reader earlier to overlap more).
    """
    from core.localview import ImageError

    # The engine's matrices are small: multi-threaded BLAS only adds contention (2-5x slower on a busy machine).
    with threadpool_limits(limits=1, user_api="blas"), contextlib.ExitStack() as stack:
        opened = log if isinstance(log, MissionLog) else stack.enter_context(open_log(log, topics))
        _check_modalities(opened, engine.params)
        known = LogIdentity.of(opened) if identity is None else identity
        total = known.frames
        end = total if stop is None else min(stop, total)
        if frames is None:
            frames = stack.enter_context(opened.frames_ahead(start, total if overrun is not None else end))
        if reckoning is None:
            reckoning = DeadReckoning(math.radians(engine.params.exp_initial_em_deg))
        count = 0
        for frame in frames:
            if start + count >= end and (overrun is None or not overrun()):
                break
            stamp = frame.stamp_ns * 1e-9
            try:
                result = engine.step(frame.image, frame.motion, stamp, frame.sonar)
            except ImageError as err:  # images smaller than the preset's template or crop
                msg = f"{opened.path}: frame {start + count} cannot be processed with these parameters: {err}"
                raise InputError(msg) from err
            reckoning.add(stamp, result.motion)
            if on_step is not None:
                swapped = on_step(frame, result)
                if swapped is not None:
                    engine = swapped
            count += 1
            if progress is not None:
                progress(count, max(end - start, count))
        report = getattr(frames, "report", None)  # a reader ahead counted in its own copy of the log
        dropped = opened.report if report is None else report
    return EngineRun(engine, count, reckoning, known, dropped)


def _check_modalities(opened: MissionLog, params: Params) -> None:
    """Raise InputError when the log maps a sonar topic and the front-end has no sonar modality."""
    if opened.mapping.sonar is not None and params.frontend != "sdr-htm":
        msg = (f"{opened.path}: a sonar topic ({opened.mapping.sonar}) is a modality of the sdr-htm front-end "
               f"only: use the preset poseidon or neoslam, or leave sonar= out of the topics")
        raise InputError(msg)


def _new_engine(params: Params) -> Engine:
    """Return a new session's engine (origin 0); an invalid front-end setting raises ``ConfigError``."""
    from core.engine import Engine

    return Engine(params, origin=0)


def process_log(
    log_path: str | Path,
    params: Params,
    *,
    topics: Mapping[str, str] | None = None,
    out: str | Path | None = None,
    progress: ProgressCallback | None = None,
) -> ProcessResult:
    """Run the engine over one log without a database; optionally write the map JSON to ``out``.

    The log's frames are read ahead from the moment it is open, while the engine's libraries and the kernels
    load (:func:`load_frontend`); the lvc engine is made then (it raises nothing), sdr-htm's before the log opens.

    Raises:
        InputError: the log cannot be read (``IngestError``) or the parameters are invalid.
    """
    name = log_stem(log_path)
    frame_rows: list[tuple[float, int, int]] = []  # the map JSON "frames" extension

    def record(frame: Frame, result: StepResult) -> None:
        frame_rows.append((frame.stamp_ns * 1e-9, int(result.template), int(result.template_created)))

    engine = _new_engine(params) if params.frontend != "lvc" else None  # torch's front-end checks its settings first
    with open_log(log_path, topics) as opened:
        _check_modalities(opened, params)
        with opened.frames_ahead() as frames:
            if engine is None:
                engine = _new_engine(params)
            load_frontend(params, opened.count_frames())
            started = time.perf_counter()
            identity = LogIdentity.of(opened)
            run = run_engine(engine, opened, progress=progress, on_step=record, frames=frames, identity=identity)
    frames_run, reckoning = run.frames, run.reckoning
    if frames_run == 0:
        msg = f"{log_path}: the camera topic has no frames"
        raise InputError(msg)
    engine.settle()
    snapshot = engine.snapshot()
    document = map_json(
        params=params.to_dict(),
        snapshot=snapshot,
        sessions=[SessionInfo(name=name, log_sha256=identity.sha256, frames=frames_run)],
        session_name_by_origin={0: name},
        odometry=reckoning.array(),
        frames=frame_rows,
    )
    if out is not None:
        write_map_json(out, document)
    src = snapshot["em_link_from"]
    return ProcessResult(
        frames=frames_run,
        templates=engine.template_count,
        experiences=engine.experience_count,
        links=int(src.shape[0]),
        loop_closures=engine.loop_closures,
        map_name=name,
        seconds=time.perf_counter() - started,
        engine=engine,
        document=document,
        frames_run=frames_run,
        dropped=run.dropped,
    )

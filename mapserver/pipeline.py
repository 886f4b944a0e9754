"""The one place that runs a mission log through the engine, the store and the merger.

Both faces (``mapserver process`` and the REST API's jobs) call :func:`process_log`.
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

from core import ConfigError, Engine, Params
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
    with open_log(log_path, topics) as log:
        total = log.count_frames()
        end = total if stop is None else min(stop, total)
        reckoning = DeadReckoning(math.radians(engine.params.exp_initial_em_deg))
        count = 0
        for frame in log.frames(start, end):
            stamp = frame.stamp_ns * 1e-9
            result = engine.step(frame.image, frame.motion, stamp)
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
    frames, reckoning, info = run_engine(engine, log_path, topics=topics, progress=progress)
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

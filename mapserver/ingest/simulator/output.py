"""Running a scenario: render every frame, write the logs, the ground-truth TUM files and scenario.json.

Everything is written into a fresh temporary directory beside the target and moved into it at the end
(scenario.json last), so a failure or an interruption leaves the target as it was. Images are rendered
lazily while the log is written, so memory does not grow with the session length.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from mapserver.errors import InputError
from mapserver.formats import write_tum
from mapserver.ingest.simulator.drive import Drive, VehicleErrors, simulate_drive
from mapserver.ingest.simulator.navsensors import nav_messages
from mapserver.ingest.simulator.render import expose, expose_sonar, render, render_sonar
from mapserver.ingest.simulator.scenarios import SCENARIOS, Plan, SessionPlan
from mapserver.ingest.writer import SUFFIXES, LogFormat, write_log

ProgressCallback = Callable[[int, int], None]

SCENARIO_FILE = "scenario.json"


def plan_scenario(
    scenario: str, seed: int = 0, *, scale: float = 1.0, params: Mapping[str, float] | None = None
) -> Plan:
    """Build a scenario's plan (world, routes, sessions) without rendering anything.

    Args:
        scenario: a name from :data:`~.scenarios.SCENARIOS`.
        seed: the seed (same seed, same world and sessions).
        scale: route and world size factor (> 0).
        params: scenario parameter overrides (names as in ``SCENARIOS[scenario].defaults``).

    Returns:
        The plan.

    Raises:
        InputError: unknown scenario (the valid ones are listed), unknown parameter or bad value.

    """
    definition = SCENARIOS.get(scenario)
    if definition is None:
        msg = f"unknown scenario {scenario!r} (valid: {', '.join(SCENARIOS)})"
        raise InputError(msg)
    if not scale > 0 or not np.isfinite(scale):
        msg = f"scale must be a positive number, got {scale!r}"
        raise InputError(msg)
    effective = dict(definition.defaults)
    for key, value in (params or {}).items():
        if key not in effective:
            msg = f"unknown parameter {key!r} for scenario {scenario!r} (valid: {', '.join(effective) or 'none'})"
            raise InputError(msg)
        number = float(value)
        if not np.isfinite(number):
            msg = f"parameter {key!r} must be a finite number, got {value!r}"
            raise InputError(msg)
        effective[key] = number
    return definition.build(int(seed), float(scale), effective)


def plan_vehicle(plan: Plan, seed: int) -> VehicleErrors:
    """Return the systematic odometry errors of the scenario's vehicle (every session of a plan shares them)."""
    return VehicleErrors.draw(plan.noise, np.random.default_rng([seed, 3000]))


def simulate_session(plan: Plan, session: SessionPlan, index: int, seed: int) -> Drive:
    """Simulate one session of a plan (trajectory, odometry, ground truth, camera stamps)."""
    rng = np.random.default_rng([seed, 1000 + index])
    return simulate_drive(session.spec, plan.noise, plan.rates, session.t0_ns, rng, plan_vehicle(plan, seed))


def render_frames(
    plan: Plan, drive: Drive, seed: int, index: int, progress: Callable[[], None] | None = None
) -> Iterator[tuple[int, npt.NDArray[np.uint8]]]:
    """Yield ``(stamp_ns, image)`` for every frame of a drive, rendered on demand."""
    rng = np.random.default_rng([seed, 2000 + index])
    start_ns = drive.odometry[0].stamp_ns if drive.odometry else 0
    world, exposure = plan.world, 1.0
    for stamp, pose, gain in zip(drive.frame_stamps_ns.tolist(), drive.frame_poses, drive.frame_gain, strict=True):
        if plan.lighting is not None:
            world, exposure = plan.lighting.at(plan.world, (int(stamp) - start_ns) * 1e-9)
        radiance = render(world, plan.camera, float(pose[0]), float(pose[1]), float(pose[2]), float(pose[3]))
        if progress is not None:
            progress()
        yield int(stamp), expose(radiance, float(gain) * exposure, plan.noise.pixel_noise, rng)


def render_sonar_frames(plan: Plan, drive: Drive, seed: int, index: int) -> Iterator[tuple[int, npt.NDArray[np.uint8]]]:
    """Yield ``(stamp_ns, sonar image)`` at every camera frame of a drive (none when the plan has no sonar)."""
    sonar = plan.sonar
    if sonar is None:
        return
    rng = np.random.default_rng([seed, 3000 + index])
    for stamp, pose in zip(drive.frame_stamps_ns.tolist(), drive.frame_poses, strict=True):
        echo = render_sonar(plan.world, sonar, float(pose[0]), float(pose[1]), float(pose[2]), float(pose[3]))
        yield int(stamp), expose_sonar(echo, sonar, rng)


def write_ground_truth(path: Path, drive: Drive) -> None:
    """Write a drive's ground truth as a TUM file (stamp, position, orientation quaternion)."""
    gt = drive.ground_truth
    write_tum(
        path,
        np.array([g.stamp_ns for g in gt], dtype=np.int64) * 1e-9,
        np.array([[g.x, g.y, g.z] for g in gt]),
        np.array([[g.qx, g.qy, g.qz, g.qw] for g in gt]),
    )


def simulate(
    scenario: str,
    out_dir: str | os.PathLike[str],
    *,
    seed: int = 0,
    fmt: LogFormat = "bag",
    scale: float = 1.0,
    params: Mapping[str, float] | None = None,
    progress: ProgressCallback | None = None,
    only: Sequence[str] | None = None,
) -> dict[str, Any]:
    """Simulate a scenario and write its logs, ground truth and ``scenario.json`` into ``out_dir``.

    Each log (``<name>.<fmt>``) holds ``/robot/camera/image`` (mono8), ``/robot/odom`` (nav_msgs/Odometry,
    noisy twist and the pose integrated from it), ``/robot/ground_truth`` (PoseStamped, world frame) and,
    where the plan has a sonar, ``/robot/sonar/image`` (mono8, at the camera's stamps); the
    ground truth is also written as ``<name>.tum``. Existing files of the same names are replaced.

    Args:
        scenario: scenario name.
        out_dir: target directory (created).
        seed: random seed: the same seed gives the same files' contents.
        fmt: ``bag``, ``db3`` or ``mcap``.
        scale: route and world size factor.
        params: scenario parameter overrides.
        progress: ``progress(done, total)`` called per rendered frame.
        only: write only the logs of these session names (``single`` for the single-session log); the
            others are listed in scenario.json with ``"log": null`` (tests use this to save time).

    Returns:
        The scenario.json document: ``{"scenario", "preset", "sessions": [{"name", "log", "ground_truth",
        "frames", ...}], "single": {...} or None, "seed", "format", "scale", "params", ...}`` with paths
        relative to ``out_dir``.

    Raises:
        InputError: unknown scenario, parameter or format.

    """
    if fmt not in SUFFIXES:
        msg = f"unknown log format {fmt!r} (valid: {', '.join(SUFFIXES)})"
        raise InputError(msg)
    plan = plan_scenario(scenario, seed, scale=scale, params=params)
    target = _checked_target(Path(out_dir))
    jobs, wanted = _session_jobs(plan, scenario, only)
    drives = {index: simulate_session(plan, session, index, seed) for index, session in wanted}
    tick = _frame_ticker(sum(len(d.frame_stamps_ns) for d in drives.values()), progress)
    with _temporary_dir_beside(target) as temp:
        entries = _write_sessions(temp, fmt, plan, jobs, wanted, drives, seed, tick)
        document = _scenario_document(plan, entries, jobs, seed, fmt, scale)
        (temp / SCENARIO_FILE).write_text(json.dumps(document, indent=1) + "\n", encoding="utf-8")
        _move_into(temp, target)
    return document


def _checked_target(target: Path) -> Path:
    """Return the target directory (existing or not) after checking that it is not a file.

    Raises:
        InputError: ``target`` exists and is not a directory.
    """
    if target.exists() and not target.is_dir():
        msg = f"--out {str(target)!r} exists and is not a directory"
        raise InputError(msg)
    return target


def _frame_ticker(total: int, progress: ProgressCallback | None) -> Callable[[], None]:
    """Return the per-frame callback that counts rendered frames and reports ``progress(done, total)``."""
    done = 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total)

    return tick


@contextlib.contextmanager
def _temporary_dir_beside(target: Path) -> Iterator[Path]:
    """Yield a fresh temporary directory beside ``target`` (its parent created); remove what is left of it on exit."""
    target.parent.mkdir(parents=True, exist_ok=True)
    temp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
    try:
        yield temp
    finally:
        with contextlib.suppress(FileNotFoundError):
            shutil.rmtree(temp)


def _session_jobs(
    plan: Plan, scenario: str, only: Sequence[str] | None
) -> tuple[list[tuple[int, SessionPlan]], list[tuple[int, SessionPlan]]]:
    """Return every session of the plan (the single-session log last when it is not one of them) and those to write.

    Raises:
        InputError: ``only`` names a session the scenario does not have.
    """
    jobs: list[tuple[int, SessionPlan]] = list(enumerate(plan.sessions))
    if plan.single is not None and all(s is not plan.single for s in plan.sessions):
        jobs.append((len(plan.sessions), plan.single))
    if only is not None:
        unknown = sorted(set(only) - {s.name for _, s in jobs})
        if unknown:
            msg = f"unknown session(s) {', '.join(unknown)} for scenario {scenario!r}"
            raise InputError(msg)
    return jobs, [(i, s) for i, s in jobs if only is None or s.name in only]


def _write_sessions(
    temp: Path,
    fmt: LogFormat,
    plan: Plan,
    jobs: list[tuple[int, SessionPlan]],
    wanted: list[tuple[int, SessionPlan]],
    drives: dict[int, Drive],
    seed: int,
    tick: Callable[[], None],
) -> dict[int, dict[str, Any]]:
    """Write the ``wanted`` sessions' logs into ``temp``; return every session's scenario.json entry by index.

    The sessions of ``jobs`` not written get an entry with ``"log": null``.
    """
    entries: dict[int, dict[str, Any]] = {
        index: {"name": session.name, "log": None, "ground_truth": None, **session.info} for index, session in jobs
    }
    for index, session in wanted:
        entries[index] = _write_session(temp, fmt, plan, session, (drives[index], seed, index), tick)
    return entries


def _write_session(
    temp: Path, fmt: LogFormat, plan: Plan, session: SessionPlan, run: tuple[Drive, int, int], tick: Callable[[], None]
) -> dict[str, Any]:
    """Write one session's log and ground truth into ``temp``; return its scenario.json entry.

    ``run`` is (the simulated drive, the seed, the session's index in the plan).
    """
    drive, seed, index = run
    log_name = f"{session.name}{SUFFIXES[fmt]}"
    gt_name = f"{session.name}.tum"
    extra = []
    if plan.navigation is not None:
        end_s = (drive.odometry[-1].stamp_ns - session.t0_ns) * 1e-9
        extra = nav_messages(plan.navigation, session.spec, session.t0_ns, plan.noise, end_s, seed, index)
    write_log(temp / log_name, fmt, render_frames(plan, drive, seed, index, tick),
              drive.odometry if plan.odometry else (), drive.ground_truth,
              sonar=render_sonar_frames(plan, drive, seed, index),
              sonar_topic=plan.sonar_topic, image_encoding=plan.image_encoding,
              jpeg_quality=plan.jpeg_quality, extra=extra)  # fmt: skip
    write_ground_truth(temp / gt_name, drive)
    return {
        "name": session.name,
        "log": log_name,
        "ground_truth": gt_name,
        "frames": len(drive.frame_stamps_ns),
        "duration_s": round((drive.odometry[-1].stamp_ns - drive.odometry[0].stamp_ns) * 1e-9, 3),
        "start_stamp": drive.odometry[0].stamp_ns * 1e-9,
        "odometry_errors": drive.errors,
        **session.info,
    }


def _scenario_document(
    plan: Plan,
    entries: dict[int, dict[str, Any]],
    jobs: list[tuple[int, SessionPlan]],
    seed: int,
    fmt: LogFormat,
    scale: float,
) -> dict[str, Any]:
    """Return scenario.json: the sessions' entries, the single-session log's, camera, odometry and sonar settings."""
    sessions = [entries[i] for i, _ in enumerate(plan.sessions)]
    single = None
    if plan.single is not None:
        index = next((i for i, s in jobs if s is plan.single), None)
        single = {k: v for k, v in entries[index].items() if k != "name"} if index is not None else None
    return {
        "scenario": plan.scenario,
        "preset": plan.preset,
        "sessions": sessions,
        "single": single,
        "seed": int(seed),
        "format": fmt,
        "scale": float(scale),
        "params": plan.params,
        "camera": {
            "width": plan.camera.width, "height": plan.camera.height, "hfov_deg": plan.camera.hfov_deg,
            "max_range_m": plan.camera.max_range, "rate_hz": plan.rates.camera_hz,
            "encoding": plan.image_encoding,
            **({"jpeg_quality": plan.jpeg_quality} if plan.image_encoding == "jpeg" else {}),
        },
        "odometry_hz": plan.rates.odom_hz,
        **({} if plan.sonar is None else {"sonar": {
            "topic": plan.sonar_topic, "beams": plan.sonar.beams, "bins": plan.sonar.bins,
            "hfov_deg": plan.sonar.hfov_deg, "max_range_m": plan.sonar.max_range}}),
        "vehicle_odometry_errors": dataclasses.asdict(plan_vehicle(plan, seed)),
        **({} if plan.navigation is None else {"navigation": plan.navigation.info()}),
        **({} if plan.odometry else {"odometry": None}),
        **plan.info,
    }  # fmt: skip


def _move_into(temp: Path, target: Path) -> None:
    """Move every file of ``temp`` into ``target`` (created), scenario.json last."""
    if not target.exists():
        temp.chmod(0o755)  # mkdtemp makes it private
        os.replace(temp, target)
        return
    names = [*sorted(p.name for p in temp.iterdir() if p.name != SCENARIO_FILE), SCENARIO_FILE]
    for name in names:
        dst = target / name
        if dst.is_dir() and not dst.is_symlink():
            shutil.rmtree(dst)
        os.replace(temp / name, dst)

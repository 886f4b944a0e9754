"""Tiny mission logs for the API tests: a textured strip seen from a vehicle driving a circle.

Views of one place are the same on every lap and different places differ, so a log of more than
one lap closes loops. Everything is generated (seeded) in tmp_path; nothing binary is committed.
"""

from __future__ import annotations

import io
import math
import tarfile
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from mapserver.ingest.frames import PoseSample
from mapserver.ingest.writer import OdomSample, write_log

T0_NS = 1_700_000_000_000_000_000
PERIMETER_M = 24.0
PX_PER_M = 8.0


def _texture(seed: int, height: int = 20, columns: int = int(PERIMETER_M * PX_PER_M)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = rng.random((height, columns))
    kernel = np.ones(5) / 5.0
    smooth = np.stack([np.convolve(np.concatenate([r[-2:], r, r[:2]]), kernel, "valid") for r in base])
    return (40 + 180 * smooth).astype(np.uint8)


def write_strip_log(path: Path, *, laps: float = 1.3, seed: int = 3, rate_hz: float = 2.0, fmt: str = "bag",
                    width: int = 64, t0_ns: int = T0_NS, directory: bool = False,
                    odometry_edit: Callable[[list[OdomSample]], list[OdomSample]] | None = None,
                    pose_only: bool = False, truth_hz: float = 0.0,
                    truth_frame: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Path:  # fmt: skip
    """Write a log of the strip world driven ``laps`` times around (images at ``rate_hz``, odometry 10 Hz).

    ``odometry_edit`` gets the odometry samples and returns the ones written; ``pose_only`` writes zero twists.
    ``truth_hz`` > 0 adds a ground-truth topic at that rate: the same circle, in a frame turned by
    ``truth_frame[0]`` rad and shifted by ``truth_frame[1:]`` m from the odometry's.
    """
    texture = _texture(seed)
    columns = texture.shape[1]
    speed = 1.0
    radius = PERIMETER_M / (2 * math.pi)
    wz = speed / radius
    duration = laps * PERIMETER_M / speed
    count = int(duration * rate_hz)
    images = []
    for i in range(count):
        start = round(speed * i / rate_hz * PX_PER_M) % columns
        images.append((t0_ns + round(i / rate_hz * 1e9), texture[:, (start + np.arange(width)) % columns]))
    odometry = []
    for j in range(int(duration * 10) + 2):
        t = j / 10
        yaw = wz * t
        odometry.append(OdomSample(t0_ns + round(t * 1e9), radius * math.sin(yaw), radius * (1 - math.cos(yaw)),
                                   0.0, yaw, speed, 0.0, 0.0, wz))  # fmt: skip
    if odometry_edit is not None:
        odometry = odometry_edit(odometry)
    truth = strip_truth(duration, truth_hz, truth_frame, t0_ns) if truth_hz > 0 else []
    return write_log(path, fmt, images, odometry, truth, directory=directory,  # type: ignore[arg-type]
                     pose_only_odometry=pose_only)  # fmt: skip


def strip_truth(duration: float, hz: float, frame: tuple[float, float, float], t0_ns: int = T0_NS) -> list[PoseSample]:
    """Return the strip log's ground truth: its circle at ``hz`` for ``duration`` s, in ``frame`` (yaw, x, y)."""
    radius = PERIMETER_M / (2 * math.pi)
    turn, dx, dy = frame
    out = []
    for j in range(int(duration * hz) + 1):
        t = j / hz
        yaw = t / radius  # 1 m/s
        x, y = radius * math.sin(yaw), radius * (1 - math.cos(yaw))
        heading = yaw + turn
        out.append(PoseSample(t0_ns + round(t * 1e9), math.cos(turn) * x - math.sin(turn) * y + dx,
                              math.sin(turn) * x + math.cos(turn) * y + dy, 0.0, 0.0, 0.0,
                              math.sin(heading / 2), math.cos(heading / 2)))  # fmt: skip
    return out


def zip_directory(directory: Path, out: Path, *, prefix: str | None = None) -> Path:
    """Zip a directory (entries under ``prefix``/, default the directory's name); ``out`` must lie outside it."""
    assert directory.resolve() not in out.resolve().parents, "the archive would contain itself"
    root = directory.name if prefix is None else prefix
    with zipfile.ZipFile(out, "w") as zf:
        for file in sorted(directory.rglob("*")):
            if file.is_file():
                zf.write(file, f"{root}/{file.relative_to(directory).as_posix()}" if root else file.name)
    return out


def tar_bytes(members: list[tuple[tarfile.TarInfo, bytes | None]]) -> bytes:
    """Return a tar archive holding ``members`` (data for regular files, None otherwise)."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tf:
        for info, data in members:
            if data is not None:
                info.size = len(data)
                tf.addfile(info, io.BytesIO(data))
            else:
                tf.addfile(info)
    return buffer.getvalue()

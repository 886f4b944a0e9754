"""Build and run OpenRatSLAM's C++ core (a local copy the user provides) under our offline driver.

Nothing of OpenRatSLAM is stored in this repository: :func:`build_driver` compiles our ``driver.cpp``
against the ``src/ratslam`` sources of a local copy of davidmball/ratslam into a temporary folder.
Obtain a copy with ``git clone https://github.com/davidmball/ratslam /tmp/ratslam`` (GPL v3; keep it
outside this repository). The C++ needs Boost's headers (``apt-get install libboost-dev``) and g++.
"""

from __future__ import annotations

import csv
import hashlib
import struct
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from core import Params
from core.angles import wrap_angle_below_pi

HERE = Path(__file__).resolve().parent
DRIVER = HERE / "driver.cpp"
CORE_SOURCES = ("posecell_network.cpp", "local_view_match.cpp", "experience_map.cpp")
# OpenRatSLAM reads these keys from the [ratslam] section (their names are ours too).
CXX_KEYS = (
    "image_crop_x_min", "image_crop_x_max", "image_crop_y_min", "image_crop_y_max", "template_x_size",
    "template_y_size", "vt_match_threshold", "vt_shift_match", "vt_step_match", "vt_normalisation",
    "vt_patch_normalise", "vt_min_patch_normalisation_std", "vt_panoramic", "vt_active_decay", "pc_dim_xy",
    "pc_dim_th", "pc_w_e_dim", "pc_w_i_dim", "pc_w_e_var", "pc_w_i_var", "pc_global_inhib",
    "pc_vt_inject_energy", "pc_cell_x_size", "pc_vt_restore", "exp_delta_pc_threshold", "exp_correction",
    "exp_loops", "exp_initial_em_deg",
)


class HarnessError(RuntimeError):
    """The C++ core cannot be found, built or run."""


def check_copy(ratslam: Path) -> Path:
    """Return ``ratslam/src`` after checking that the core sources are there."""
    src = ratslam / "src"
    missing = [name for name in CORE_SOURCES if not (src / "ratslam" / name).is_file()]
    if missing:
        msg = (
            f"{ratslam}: no OpenRatSLAM core ({', '.join(missing)} missing under src/ratslam). Obtain a copy "
            "with: git clone https://github.com/davidmball/ratslam /tmp/ratslam"
        )
        raise HarnessError(msg)
    return src


def build_driver(ratslam: Path, build_dir: Path) -> Path:
    """Compile our driver with the core's three non-graphics sources; reuse a binary built from the same inputs.

    ``-ftrivial-auto-var-init=zero`` gives OpenRatSLAM's one uninitialised loop counter
    (``convert_view_to_view_template``'s ``for (unsigned int i; ...)``) the value 0 it needs.
    """
    src = check_copy(ratslam)
    sources = [DRIVER] + [src / "ratslam" / name for name in CORE_SOURCES]
    digest = hashlib.sha256()
    for path in sources + [src / "ratslam" / h for h in ("posecell_network.h", "local_view_match.h",
                                                        "experience_map.h")]:
        digest.update(path.read_bytes())
    build_dir.mkdir(parents=True, exist_ok=True)
    binary = build_dir / f"ratslam_driver_{digest.hexdigest()[:12]}"
    if binary.exists():
        return binary
    cmd = ["g++", "-O2", "-std=c++14", "-ftrivial-auto-var-init=zero", "-w", f"-I{src}", "-o", str(binary)]
    cmd += [str(s) for s in sources]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        msg = f"building the driver failed (Boost headers: apt-get install libboost-dev):\n{done.stderr[-2000:]}"
        raise HarnessError(msg)
    return binary


def write_ini(params: Params, path: Path) -> None:
    """Write the OpenRatSLAM keys of ``params`` as an INI ``[ratslam]`` section."""
    values = params.to_dict()
    lines = ["[ratslam]"]
    for key in CXX_KEYS:
        value = values[key]
        if isinstance(value, bool):
            value = int(value)
        if isinstance(value, float) and value.is_integer():
            value = int(value)  # some of OpenRatSLAM's keys are ints (pc_w_e_var) and "1.0" does not parse
        lines.append(f"{key}={value!r}" if isinstance(value, float) else f"{key}={value}")
    path.write_text("\n".join(lines) + "\n")


class FrameWriter:
    """Writes the driver's input: decoded frames and per-frame odometry (format in driver.cpp)."""

    def __init__(self, path: Path, frames: int) -> None:
        self.path = path
        self.frames = frames
        self.count = 0
        self._file: Any = None

    def add(self, stamp: float, dx: float, dyaw: float, dt: float, image: np.ndarray) -> None:
        """Append one frame: OpenRatSLAM takes speeds, so the motion is sent as (dx/dt, dyaw/dt, dt)."""
        pixels = np.ascontiguousarray(image, dtype=np.uint8)
        if self._file is None:
            h, w = pixels.shape[:2]
            channels = 1 if pixels.ndim == 2 else 3
            self._file = self.path.open("wb")
            self._file.write(b"RSLF" + struct.pack("<5I", 1, self.frames, w, h, channels))
        v, w_rot = (dx / dt, dyaw / dt) if dt > 0 else (0.0, 0.0)
        self._file.write(struct.pack("<4d", stamp, v, w_rot, dt))
        self._file.write(pixels[..., :3].tobytes() if pixels.ndim == 3 else pixels.tobytes())
        self.count += 1

    def close(self) -> None:
        """Close the file; the frame count must match the header."""
        if self._file is not None:
            self._file.close()
        if self.count != self.frames:
            msg = f"{self.path}: {self.count} frames written, header says {self.frames}"
            raise HarnessError(msg)


@dataclass
class CxxRun:
    """The driver's outputs."""

    trace: dict[str, np.ndarray]
    experiences: np.ndarray  # (N, 3) x, y, th
    links: np.ndarray  # (L, 6) from, to, d, heading, facing, dt
    frames_per_s: float
    summary: str


def read_csv(path: Path) -> dict[str, np.ndarray]:
    """Read a numeric CSV with a header into columns."""
    with path.open() as f:
        rows = list(csv.reader(f))
    header, body = rows[0], rows[1:]
    data = np.array([[float(x) for x in r] for r in body], dtype=np.float64).reshape(len(body), len(header))
    return {name: data[:, i] for i, name in enumerate(header)}


def run_driver(binary: Path, ini: Path, frames: Path, out: Path) -> CxxRun:
    """Run the driver and read its trace and final map."""
    out.mkdir(parents=True, exist_ok=True)
    done = subprocess.run([str(binary), str(ini), str(frames), str(out)], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        msg = f"driver failed ({done.returncode}): {done.stderr[-2000:]}"
        raise HarnessError(msg)
    summary = done.stdout.strip().splitlines()[-1]
    fps = float(summary.rsplit("frames_per_s=", 1)[1])
    exps = read_csv(out / "experiences.csv")
    links = read_csv(out / "links.csv")
    exp_arr = np.stack([exps["x_m"], exps["y_m"], exps["th_rad"]], axis=1) if exps["id"].size else np.zeros((0, 3))
    link_cols = ("from", "to", "d", "heading_rad", "facing_rad", "delta_time_s")
    link_arr = np.stack([links[c] for c in link_cols], axis=1) if links["from"].size else np.zeros((0, 6))
    return CxxRun(read_csv(out / "trace.csv"), exp_arr, link_arr, fps, summary)


def wrapped(delta: np.ndarray, period: float) -> np.ndarray:
    """Wrap differences into [-period/2, period/2)."""
    return (delta + period / 2.0) % period - period / 2.0


def angle_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Signed smallest angle a − b."""
    return wrap_angle_below_pi(np.asarray(a) - np.asarray(b))

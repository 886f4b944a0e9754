"""Issue 17 on an accelerator: the sdr-htm front-end on CPU and CUDA, determinism and throughput.

Usage:
  python bench/neocortex_device.py extract LOG... --out FRAMES.npz   # here: a log's frames as plain arrays
  python bench/neocortex_device.py run FRAMES.npz [--devices cpu,cuda] [--repeat 2] [--shufflenet-frames 64]

``extract`` reads logs with the project's reader (rosbags) and writes their frames (images, motions, stamps)
into one ``.npz``, so that ``run`` needs only ``core`` (numpy, scipy, torch, numba): the accelerator machine
has no rosbags. ``run`` processes the frames with ``poseidon`` (weight-free encoder) once per device and
``--repeat`` times on CUDA, and prints for each: frames/s end to end, the number of view cells and
experiences, and a SHA-256 over every array of the final snapshot (the map bit for bit). Then it times the
ShuffleNetV2 x1.0 encoder (224×224, stage 3) alone on each device, with weights the script creates (random;
a throughput figure, not a recognition one). Last stdout line: one JSON object.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


HIDDEN = ("cells", "poses", "array_sha256")
"""Per-run figures written to ``--out`` only."""


def extract(logs: list[Path], out: Path) -> None:
    """Write the frames of ``logs`` (in turn) as arrays: images (N, H, W), motion (N, 5), stamps (N,), log (N,)."""
    from mapserver.ingest.reader import open_log

    images, motions, stamps, index = [], [], [], []
    for k, path in enumerate(logs):
        with open_log(path) as log:
            for frame in log.frames():
                m = frame.motion
                images.append(frame.image)
                motions.append([m.dx, m.dy, m.dz, m.dyaw, m.dt] if m is not None else [np.nan] * 5)
                stamps.append(frame.stamp_ns)
                index.append(k)
    np.savez_compressed(out, images=np.stack(images), motions=np.array(motions), stamps=np.array(stamps),
                        log=np.array(index))  # fmt: skip
    print(f"{len(images)} frames → {out}")


def _digest(snapshot: dict[str, Any]) -> str:
    h = hashlib.sha256()
    for key in sorted(snapshot):
        value = np.ascontiguousarray(np.asarray(snapshot[key]))
        h.update(key.encode())
        h.update(str(value.dtype).encode())
        h.update(value.tobytes())
    return h.hexdigest()


def _motion(row: np.ndarray) -> Any:
    """Return the ``core.motion.Motion`` of an extracted motion row (None: the log had no odometry)."""
    from core.motion import Motion

    return None if np.isnan(row[0]) else Motion(*(float(v) for v in row))


def _run_engine(frames: dict[str, np.ndarray], device: str) -> dict[str, Any]:
    from core import Engine, preset

    params = preset("poseidon").replace(frontend_device=device)
    engines: dict[int, Any] = {}
    cells: list[int] = []
    started = time.perf_counter()
    for image, motion, stamp, log in zip(frames["images"], frames["motions"], frames["stamps"], frames["log"],
                                         strict=True):  # fmt: skip
        if int(log) not in engines:  # each log its own session
            engines[int(log)] = Engine(params)
        engine = engines[int(log)]
        cells.append(engine.step(image, _motion(motion), int(stamp) * 1e-9).template)
    _sync(device)
    seconds = time.perf_counter() - started
    n = len(frames["stamps"])
    snaps = [engines[k].snapshot() for k in sorted(engines)]
    return {
        "device": device, "frames": n, "frames_per_s": round(n / seconds, 1),
        "view_cells": [e.template_count for _, e in sorted(engines.items())],
        "experiences": [e.experience_count for _, e in sorted(engines.items())],
        "sha256": [_digest(s) for s in snaps], "cells": cells,
        "array_sha256": [{k: _digest({k: v}) for k, v in sorted(s.items())} for s in snaps],
        "poses": [np.asarray(s["em_pose"]).tolist() for s in snaps],
    }  # fmt: skip


def _time_shufflenet(frames: dict[str, np.ndarray], device: str, count: int) -> dict[str, Any]:
    """Time ``poseidon`` with the ShuffleNetV2 x1.0 encoder (random weights, saved by the script)."""
    import torch

    from core import Engine, preset
    from core.neocortex.backbones import ShuffleNetV2, build_backbone, preprocess

    with tempfile.TemporaryDirectory() as tmp:
        weights = Path(tmp) / "shufflenet_v2_x1_0.pth"
        torch.manual_seed(0)
        torch.save(ShuffleNetV2().state_dict(), weights)
        params = preset("poseidon").replace(frontend_backbone="shufflenetv2", frontend_weights=str(weights),
                                                frontend_device=device)  # fmt: skip
        engine = Engine(params)
        net = build_backbone("shufflenetv2", weights, torch.device(device))
        x = preprocess(frames["images"][0], torch.device(device))
        with torch.no_grad():
            for _ in range(5):
                net.embed(x)
            _sync(device)
            started = time.perf_counter()
            for _ in range(count):
                net.embed(x)
            _sync(device)
            encoder_ms = 1000 * (time.perf_counter() - started) / count
        started = time.perf_counter()
        for image, motion, stamp in zip(frames["images"][:count], frames["motions"][:count], frames["stamps"][:count],
                                        strict=True):  # fmt: skip
            engine.step(image, _motion(motion), int(stamp) * 1e-9)
        _sync(device)
        seconds = time.perf_counter() - started
    return {"device": device, "frames": count, "engine_ms_per_frame": round(1000 * seconds / count, 2),
            "encoder_ms_per_frame": round(encoder_ms, 2), "threads": torch.get_num_threads()}  # fmt: skip


def _sync(device: str) -> None:
    if device == "cuda":
        import torch

        torch.cuda.synchronize()


def run(path: Path, devices: list[str], repeat: int, shufflenet_frames: int, out: Path | None = None) -> None:
    """Process the frames on each device (CUDA ``repeat`` times) and time the ShuffleNetV2 encoder.

    ``out``: also write every figure with each run's per-frame view cells and final experience poses (JSON).
    """
    import torch

    data = np.load(path)
    frames = {k: data[k] for k in ("images", "motions", "stamps", "log")}
    figures: dict[str, Any] = {"torch": torch.__version__, "cuda": torch.cuda.is_available(),
                               "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
                               "engine": [], "shufflenet": []}  # fmt: skip
    for device in devices:
        for _ in range(repeat if device == "cuda" else 1):
            result = _run_engine(frames, device)
            figures["engine"].append(result)
            print(json.dumps({k: v for k, v in result.items() if k not in HIDDEN}), flush=True)
    for device in devices:
        result = _time_shufflenet(frames, device, shufflenet_frames)
        figures["shufflenet"].append(result)
        print(json.dumps(result), flush=True)
    if out is not None:
        out.write_text(json.dumps(figures))
    shown = [{k: v for k, v in e.items() if k not in HIDDEN} for e in figures["engine"]]
    print(json.dumps({**figures, "engine": shown}))


def main() -> None:
    """Dispatch ``extract`` or ``run``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="verb", required=True)
    ext = sub.add_parser("extract")
    ext.add_argument("logs", nargs="+", type=Path)
    ext.add_argument("--out", type=Path, required=True)
    r = sub.add_parser("run")
    r.add_argument("frames", type=Path)
    r.add_argument("--devices", default="cpu,cuda")
    r.add_argument("--repeat", type=int, default=2)
    r.add_argument("--shufflenet-frames", type=int, default=64)
    r.add_argument("--out", type=Path, default=None, help="write the figures with per-frame view cells (JSON)")
    args = parser.parse_args()
    if args.verb == "extract":
        extract(args.logs, args.out)
    else:
        run(args.frames, args.devices.split(","), args.repeat, args.shufflenet_frames, args.out)


if __name__ == "__main__":
    main()

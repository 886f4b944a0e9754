"""Measuring multisession scenarios through the contract's commands (simulate → process --db → export/path).

Used by ``test_acceptance.py`` (reduced scale) and by ``bench/merge_acceptance.py`` (full scale, the
README figures). Everything is computed from what the commands write: stored maps exported as map
JSON, the logs' frame stamps and the simulator's ground truth (TUM).
"""

from __future__ import annotations

import contextlib
import io
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from mapserver.cli import main
from mapserver.evaluation import interpolate_poses
from mapserver.formats import read_map_json, read_tum
from mapserver.ingest import open_log


def cli_json(*argv: str) -> dict[str, Any]:
    """Run ``mapserver ARGV --json`` in this process; return the JSON result (the last stdout line).

    Raises:
        RuntimeError: the command failed (its stderr is in the message).
    """
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([*argv, "--json"])
    if code != 0:
        raise RuntimeError(f"mapserver {' '.join(argv)} exited {code}: {err.getvalue()[-2000:]}")
    return json.loads(out.getvalue().strip().splitlines()[-1])


def cli_code(*argv: str) -> tuple[int, str]:
    """Run ``mapserver ARGV`` in this process; return (exit code, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(argv))
    return code, err.getvalue()


def frame_stamps(log: Path) -> np.ndarray:
    """Return the camera frame stamps (s) of a log, in frame order."""
    with open_log(log) as opened:
        return np.array([f.stamp_ns * 1e-9 for f in opened.frames()], dtype=np.float64)


def true_xy(tum: Path, stamps: np.ndarray) -> np.ndarray:
    """Return the ground-truth (x, y, z) at the stamps (interpolated)."""
    return interpolate_poses(read_tum(tum), stamps)[:, :3]


def experiences(doc: dict[str, Any], session: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Return (positions (E, 3), stamps (E,)) of a map JSON's experiences (of one session when named)."""
    rows = [e for e in doc["experiences"] if session is None or e["session"] == session]
    xyz = np.array([[e["x"], e["y"], e["z"]] for e in rows], dtype=np.float64).reshape(-1, 3)
    return xyz, np.array([e["stamp"] for e in rows], dtype=np.float64)


def rigid_fit(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (R, t) minimising Σ‖R·src + t − dst‖² (Kabsch/Umeyama without scale; 2-D or 3-D points)."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    u, _s, vt = np.linalg.svd((src - ms).T @ (dst - md))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    fix = np.eye(src.shape[1])
    fix[-1, -1] = d
    r = vt.T @ fix @ u.T
    return r, md - r @ ms


def icp_rmse(moving: np.ndarray, fixed: np.ndarray, iterations: int = 60) -> float:
    """Return the nearest-neighbour RMSE of ``moving`` onto ``fixed`` after rigid ICP alignment (the paper's test).

    Started from the centroid-aligned principal axes in both orientations; the best result is kept.
    """
    tree = cKDTree(fixed)
    best = np.inf
    for flip in (1.0, -1.0):
        r = np.eye(moving.shape[1])
        r[0, 0] = flip
        r[1, 1] = flip
        t = fixed.mean(axis=0) - r @ moving.mean(axis=0)
        for _ in range(iterations):
            current = moving @ r.T + t
            _d, nn = tree.query(current)
            r, t = rigid_fit(moving, fixed[nn])
        d, _nn = tree.query(moving @ r.T + t)
        best = min(best, float(np.sqrt(np.mean(d * d))))
    return best


def extent(points: np.ndarray) -> float:
    """Return the map's extent: its diameter, the largest distance between two of its points (m)."""
    xy = points[:, :2]
    return float(max(np.linalg.norm(xy - p, axis=1).max() for p in xy)) if len(xy) else 0.0


@dataclass(frozen=True)
class Traversal:
    """What session 2 did after its (first) merge on ground mapped before it."""

    frames: int
    created: int

    @property
    def rate(self) -> float:
        """Return the share of those frames that created an experience."""
        return self.created / self.frames if self.frames else 0.0


def created_on(
    session_stamps: np.ndarray,
    session_xyz: np.ndarray,
    created_stamps: np.ndarray,
    after_frame: int,
    mapped_xyz: Sequence[np.ndarray],
    radius: float,
) -> Traversal:
    """Count a session's frames after ``after_frame`` within ``radius`` of ground mapped before, and those that created.

    ``mapped_xyz``: true positions of the ground mapped before (another session's frames, or this
    session's own frames before the merge). An experience's stamp is its creating frame's stamp.
    """
    near = np.zeros(session_stamps.size, dtype=bool)
    for points in mapped_xyz:
        if len(points):
            d, _ = cKDTree(points[:, :2]).query(session_xyz[:, :2])
            near |= d <= radius
    later = np.arange(session_stamps.size) > after_frame
    chosen = near & later
    created = np.isin(session_stamps, created_stamps)
    return Traversal(int(chosen.sum()), int((created & chosen).sum()))


def load_doc(path: Path) -> dict[str, Any]:
    """Read a map JSON."""
    return read_map_json(path)


def measure_ellipse(directory: Path, db_url: str, *extra: str, single: dict[str, Any] | None = None) -> dict[str, Any]:
    """Process an ellipse scenario's two sessions into ``db_url`` and measure the issue's bounds.

    ``extra``: more ``process`` flags for session 2 (``--merge-no-shift``). ``single``: the single-session
    map JSON already computed (``process single.bag --out``), else it is computed here.

    Returns:
        ``merges`` (session 2's merge list), ``s1_path`` (:class:`Traversal` on session 1's path after the
        merge), ``own_path`` (on session 2's own path before the merge), ``experiences`` /
        ``single_experiences``, ``rmse`` (ICP, merged vs single), ``extent`` (single map).
    """
    info = json.loads((directory / "scenario.json").read_text())
    s1, s2 = info["sessions"]
    cli_json("process", str(directory / s1["log"]), "--db", db_url)
    second = cli_json("process", str(directory / s2["log"]), "--db", db_url, *extra)
    merged_json = directory / f"merged{'-'.join(extra)}.json"
    cli_json("export", "--db", db_url, "--map", second["map"], "--format", "json", "--out", str(merged_json))
    merged = load_doc(merged_json)
    if single is None:
        out = directory / "single-map.json"
        cli_json("process", str(directory / info["single"]["log"]), "--out", str(out))
        single = load_doc(out)
    stamps1 = frame_stamps(directory / s1["log"])
    stamps2 = frame_stamps(directory / s2["log"])
    xyz1 = true_xy(directory / s1["ground_truth"], stamps1)
    xyz2 = true_xy(directory / s2["ground_truth"], stamps2)
    _pos2, created2 = experiences(merged, "session2")
    merges = second["merges"]
    first = int(merges[0]["frame"]) if merges else stamps2.size
    s1_path = created_on(stamps2, xyz2, created2, first, [xyz1], radius=1.0)
    own_mapped = xyz2[: first + 1]
    far_from_s1 = cKDTree(xyz1[:, :2]).query(own_mapped[:, :2])[0] > 2.0
    own_path = created_on(stamps2, xyz2, created2, first, [own_mapped[far_from_s1]], radius=1.0)
    merged_xyz, _ = experiences(merged)
    single_xyz, _ = experiences(single)
    transform_error = (np.inf, np.inf)
    if merges:
        from core.angles import wrap_angle

        truth = true_alignment(directory, s1, s2, np.radians(merged["params"]["exp_initial_em_deg"]))
        t = merges[0]["transform"]
        transform_error = (
            float(np.hypot(t["x"] - truth[0], t["y"] - truth[1])), abs(float(wrap_angle(t["yaw"] - truth[3])))
        )
    return {
        "merges": merges,
        "transform_error": transform_error,
        "s1_path": s1_path,
        "own_path": own_path,
        "own_experiences": int(np.count_nonzero(np.isin(created2, stamps2[: first + 1]))),
        "experiences": len(merged["experiences"]),
        "single_experiences": len(single["experiences"]),
        "rmse": icp_rmse(merged_xyz[:, :2], single_xyz[:, :2]),
        "extent": extent(single_xyz),
        "single": single,
    }


def true_alignment(directory: Path, loaded: dict[str, Any], partial: dict[str, Any], initial_yaw: float) -> np.ndarray:
    """Return the true T (x, y, z, yaw) taking the partial session's map frame onto the loaded session's.

    A session's map frame puts its start at the origin facing ``initial_yaw`` (``exp_initial_em_deg``):
    map = S ⊕ G⁻¹ ⊕ world with S = (0, 0, 0, initial_yaw) and G the true start pose, so
    T = S ⊕ G_loaded⁻¹ ⊕ G_partial ⊕ S⁻¹.
    """
    from core.se3 import compose, inverse, yaw_from_quaternion

    def start(session: dict[str, Any]) -> np.ndarray:
        gt = read_tum(directory / session["ground_truth"])
        return np.array([*gt.positions_xyz[0], yaw_from_quaternion(*gt.quat_xyzw[0])])

    s = np.array([0.0, 0.0, 0.0, initial_yaw])
    return compose(compose(compose(s, inverse(start(loaded))), start(partial)), inverse(s))

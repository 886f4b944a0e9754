"""How much of a map's error its closures cause, and how much its odometry leaves: the closure floor.

A merged map's APE is compared with the single route's (issue 12: ≤ 1.5×), but the two maps are made from
different odometry draws, and a draw of the single route can be half as far off as another of the same route
(``bench/reference_spread.py``). The floor separates the two: the map's own links solved by least squares
(headings, then positions, unit weights, the first experience held), once as they are (``resolved``) and once with
every active loop and merge link replaced by the relative pose of its two experiences in the ground truth
(``floor``). What the floor leaves is the odometry's: no closure, however right, takes it out. A merge that joins
its sessions as well as a single session's own closures join its laps gives ``resolved / floor`` near the single
map's. This is a measuring helper read by ``bench/lookalike_sweep.py --floor``; the solve is the relaxation's
exact fixed point, so ``resolved`` is the map as the engine settles it without its joint refinement.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from core.relaxation import solve
from core.robust import component_anchors
from core.se3 import relative, yaw_from_quaternion
from mapserver.evaluation import ape_positions, interpolate_poses
from mapserver.formats import Trajectory, read_tum

CLOSURE_KINDS = ("loop", "merge")


def true_poses(doc: dict[str, Any], truth: Trajectory) -> np.ndarray:
    """Return (N, 4) x, y, z, yaw of each exported experience in the ground truth at its stamp.

    Positions are interpolated; the heading is the nearest ground-truth row's.
    """
    stamps = np.array([e["stamp"] for e in doc["experiences"]], dtype=np.float64)
    xyz = interpolate_poses(truth, stamps, max_diff_s=0.5)
    nearest = np.abs(truth.stamps_s[None, :] - stamps[:, None]).argmin(axis=1)
    yaw = np.array([yaw_from_quaternion(*truth.quat_xyzw[i]) for i in nearest.tolist()])
    return np.column_stack([xyz, yaw])


def solve_links(start: np.ndarray, src: np.ndarray, dst: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """Return (N, 4) poses at the least-squares fixed point of the links, each component's lowest id held at ``start``.

    The relaxation's own direct solve (:func:`core.relaxation.solve`: headings, then positions given them), so
    a map re-solved on its own links is the map as the engine settles it.
    """
    return solve(start, src, dst, transform, component_anchors(start.shape[0], src, dst))


def closure_floor(doc: dict[str, Any], truth: Trajectory) -> dict[str, float]:
    """Return the APE RMSE (m) of the map as stored, re-solved on its active links, and re-solved with exact closures.

    ``doc``: a map exported as JSON (``mapserver export --format json``); ``truth``: the ground truth of its sessions.
    Links switched off (``"active": false``) are left out of both solves.
    """
    ids = {e["id"]: k for k, e in enumerate(doc["experiences"])}
    links = [link for link in doc["links"] if link.get("active", True)]
    src = np.array([ids[link["from"]] for link in links], dtype=np.int64)
    dst = np.array([ids[link["to"]] for link in links], dtype=np.int64)
    transform = np.array([link["transform"] for link in links], dtype=np.float64).reshape(-1, 4)
    stored = np.array([[e["x"], e["y"], e["z"], e["yaw"]] for e in doc["experiences"]], dtype=np.float64)
    truth_pose = true_poses(doc, truth)
    exact = transform.copy()
    closure = np.array([link["kind"] in CLOSURE_KINDS for link in links], dtype=bool)
    exact[closure] = relative(truth_pose[src[closure]], truth_pose[dst[closure]])

    def ape(pose: np.ndarray) -> float:
        return float(ape_positions(truth_pose[:, :3], pose[:, :3]).rmse)

    return {
        "stored": ape(stored),
        "resolved": ape(solve_links(stored, src, dst, transform)),
        "floor": ape(solve_links(stored, src, dst, exact)),
    }


def closure_floor_of(export: Path, truth: Path) -> dict[str, float]:
    """:func:`closure_floor` of an exported map file against a TUM ground-truth file."""
    return closure_floor(json.loads(export.read_text(encoding="utf-8")), read_tum(truth))

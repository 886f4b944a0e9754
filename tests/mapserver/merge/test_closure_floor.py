"""The closure floor (a measuring helper of the look-alike sweep) on a hand-made ring of experiences."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.se3 import relative
from mapserver.evaluation import ape_positions
from mapserver.formats import Trajectory
from tests.mapserver.merge.closure_floor import closure_floor

N = 16


def _ring() -> tuple[np.ndarray, Trajectory]:
    """(N, 4) true poses on a circle of 5 m, heading along it, and their ground truth at stamps 0..N−1 s."""
    angle = np.arange(N) * 2 * math.pi / N
    pose = np.column_stack([5 * np.cos(angle), 5 * np.sin(angle), np.zeros(N), angle + math.pi / 2])
    quat = np.column_stack([np.zeros(N), np.zeros(N), np.sin(pose[:, 3] / 2), np.cos(pose[:, 3] / 2)])
    return pose, Trajectory(np.arange(N, dtype=np.float64), pose[:, :3].copy(), quat)


def _doc(stored: np.ndarray, odometry: np.ndarray, closure: np.ndarray) -> dict:
    """An exported map: experiences at ``stored``, links i → i+1 with ``odometry`` (N−1, 4), then N−1 → 0."""
    experiences = [{"id": k, "x": p[0], "y": p[1], "z": p[2], "yaw": p[3], "stamp": float(k)}
                   for k, p in enumerate(stored.tolist())]  # fmt: skip
    links = [{"from": k, "to": k + 1, "kind": "odometry", "transform": t} for k, t in enumerate(odometry.tolist())]
    links.append({"from": N - 1, "to": 0, "kind": "loop", "transform": closure.tolist()})
    return {"experiences": experiences, "links": links}


def _true_links(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    src = np.arange(N - 1)
    return relative(pose[src], pose[src + 1]), relative(pose[N - 1], pose[0])


def test_a_wrong_closure_shows_in_the_resolved_map_and_not_in_the_floor() -> None:
    pose, truth = _ring()
    odometry, closure = _true_links(pose)
    exact = closure_floor(_doc(pose, odometry, closure), truth)
    assert exact["stored"] == pytest.approx(0.0, abs=1e-9)
    assert exact["resolved"] == pytest.approx(0.0, abs=1e-6)
    assert exact["floor"] == pytest.approx(0.0, abs=1e-6)
    wrong = closure + np.array([2.0, 0.0, 0.0, 0.0])  # the closure claims 0 → 15 is 2 m longer
    figures = closure_floor(_doc(pose, odometry, wrong), truth)
    assert figures["resolved"] > 0.05  # the least squares spreads the 2 m over the ring
    assert figures["floor"] == pytest.approx(0.0, abs=1e-6)  # the exact closure takes it out again


def test_drifting_odometry_leaves_a_floor_that_exact_closures_do_not_take_out() -> None:
    pose, truth = _ring()
    odometry, closure = _true_links(pose)
    biased = odometry.copy()
    biased[:, 3] += 0.03  # every step turns 0.03 rad too far: the ring winds up
    biased[:, 0] *= 1.05
    doc = _doc(pose, biased, closure)
    figures = closure_floor(doc, truth)
    assert figures["floor"] > 0.05
    assert figures["resolved"] == pytest.approx(figures["floor"], rel=1e-6)  # the closure was exact already
    # Links switched off are left out: with the only closure off, the chain is the odometry's alone, which its own
    # dead reckoning solves exactly (the residuals are all zero), so both solves give the dead reckoning.
    doc["links"][-1]["active"] = False
    reckoning = [pose[0]]
    for step in biased.tolist():
        x, y, z, yaw = reckoning[-1]
        c, s = math.cos(yaw), math.sin(yaw)
        reckoning.append(np.array([x + c * step[0] - s * step[1], y + s * step[0] + c * step[1], z, yaw + step[3]]))
    expected = np.array(reckoning)
    open_chain = closure_floor(doc, truth)
    assert open_chain["resolved"] == pytest.approx(ape_positions(pose[:, :3], expected[:, :3]).rmse, rel=1e-6)
    assert open_chain["floor"] == pytest.approx(open_chain["resolved"], rel=1e-9)

"""The viewer's ground-truth overlay: each session's stored ground truth in the map's frame, with its APE.

A session's APE is :func:`mapserver.evaluation.evaluate_map` of the map (the document ``evaluate`` reads:
the experiences with their stamps, poses and sessions; the map's dead reckoning when it has one session)
against the session's stored ground truth, for that session (``evaluate MAP.json --ground-truth GT.tum
--session NAME``, the same alignment and figures). The alignment maps the experiences onto the ground
truth (p_gt = R·p_map + t, Umeyama 1991); the overlay draws the ground truth in the map's frame,
p_map = Rᵀ·(p_gt − t), so it lies over the graph. Planar maps are evaluated (and drawn) in x–y.

:class:`TruthCache` keeps the evaluations per (map, version, session, ground-truth digest): a request
reads the stored rows again (a ground-truth upload changes them without changing the map), evaluates only
what changed.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from typing import Any

import numpy as np
import numpy.typing as npt

from mapserver.api.viewdata import View, ViewGraph
from mapserver.errors import InputError
from mapserver.evaluation import evaluate_map
from mapserver.formats import Trajectory
from mapserver.store import Connection, Database
from mapserver.store.ground_truth import ground_truths, session_id_by_name
from mapserver.store.sessions import get_reckoning

MAX_TRUTH_POINTS = 20_000
"""Most ground-truth points returned per session (``limit``)."""

DEFAULT_TRUTH_POINTS = 5_000


def trajectory(rows: npt.NDArray[np.float64]) -> Trajectory:
    """Return stored ground-truth rows ``[stamp, x, y, z, qx, qy, qz, qw]`` as a trajectory."""
    return Trajectory(rows[:, 0], rows[:, 1:4], rows[:, 4:8])


def map_document(graph: ViewGraph, odometry: npt.NDArray[np.float64] | None) -> dict[str, Any]:
    """Return what ``evaluate`` reads of a map JSON document, built from the viewer's graph of the map.

    ``odometry``: the ``[stamp, x, y, z]`` rows of the map's only session (the ``odometry`` extension the
    export writes for a map of one session), else None.
    """
    x, y, z, yaw = (graph.poses[:, k].tolist() for k in range(4))
    names = [graph.session_names[int(s)] for s in graph.session.tolist()]
    experiences = [
        {"id": i, "x": x[i], "y": y[i], "z": z[i], "yaw": yaw[i], "stamp": s, "session": names[i]}
        for i, s in enumerate(graph.stamp.tolist())
    ]
    doc: dict[str, Any] = {"experiences": experiences, "links": [],
                           "sessions": [{"name": n} for n in graph.session_names]}  # fmt: skip
    if odometry is not None and odometry.shape[0]:
        doc["odometry"] = odometry.tolist()
    return doc


def in_map_frame(rows: npt.NDArray[np.float64], alignment: dict[str, Any], dims: int) -> npt.NDArray[np.float64]:
    """Return the ground-truth positions in the map's frame: Rᵀ·(p − t) (z = 0 for planar maps, as evaluated)."""
    p = rows[:, 1:4].copy()
    if dims == 2:
        p[:, 2] = 0.0
    R = np.asarray(alignment["rotation"], dtype=np.float64)
    t = np.asarray(alignment["translation"], dtype=np.float64)
    return np.asarray((p - t) @ R, dtype=np.float64)


def thin(n: int, limit: int) -> npt.NDArray[np.int64]:
    """Return at most ``limit`` indices of ``range(n)``, evenly spread, the first and the last included."""
    if n <= limit:
        return np.arange(n, dtype=np.int64)
    return np.unique(np.linspace(0, n - 1, max(limit, 2)).round().astype(np.int64))


class TruthCache:
    """Thread-safe LRU of session evaluations keyed by (map id, version, session id, ground-truth digest)."""

    def __init__(self, db: Database, capacity: int = 16) -> None:
        self.db = db
        self.capacity = capacity
        self._entries: OrderedDict[tuple[int, int, int, str], dict[str, Any]] = OrderedDict()
        self._lock = threading.Lock()

    def overlay(self, graph: ViewGraph, *, view: View, limit: int) -> dict[str, Any]:
        """Return ``{"sessions": [...], "without": [names], "view"}`` for the map of ``graph``.

        Each session with ground truth: ``{"name", "rows" (stored), "drawn", "x", "y" (drawing plane, map
        frame; empty when its evaluation failed), "ape" (the ``evaluate`` result or None), "error"}``.
        """
        with self.db.read() as conn:
            ids = session_ids_of(conn, graph)
            found = ground_truths(conn=conn, session_ids=list(ids.values()))
            odometry = None
            if len(graph.session_names) == 1 and found:
                odometry, _pose = get_reckoning(conn=conn, session_id=next(iter(ids.values())))
        doc: dict[str, Any] | None = None
        sessions = []
        for name, sid in ids.items():
            if sid not in found:
                continue
            rows = found[sid]
            key = (graph.map_id, graph.version, sid, hashlib.blake2b(rows.tobytes(), digest_size=16).hexdigest())
            with self._lock:
                entry = self._entries.get(key)
            if entry is None:
                doc = doc if doc is not None else map_document(graph, odometry)
                entry = self._evaluate(doc, name, rows)
                self._keep(key, entry)
            sessions.append(self._drawn(name, rows, entry, view, limit))
        without = [n for n, sid in ids.items() if sid not in found]
        return {"sessions": sessions, "without": without, "view": view}

    @staticmethod
    def _evaluate(doc: dict[str, Any], name: str, rows: npt.NDArray[np.float64]) -> dict[str, Any]:
        try:
            return {"ape": evaluate_map(doc, trajectory(rows), session=name), "error": None}
        except InputError as err:
            return {"ape": None, "error": str(err)}

    @staticmethod
    def _drawn(name: str, rows: npt.NDArray[np.float64], entry: dict[str, Any], view: View,
               limit: int) -> dict[str, Any]:  # fmt: skip
        ape = entry["ape"]
        if ape is None:
            plane = np.zeros((0, 2))
        else:
            xyz = in_map_frame(rows, ape["alignment"], int(ape["dims"]))[thin(rows.shape[0], limit)]
            plane = xyz[:, [0, 2]] if view == "xz" else xyz[:, :2]
        return {"name": name, "rows": int(rows.shape[0]), "drawn": int(plane.shape[0]),
                "x": np.round(plane[:, 0], 4).tolist(), "y": np.round(plane[:, 1], 4).tolist(),
                "ape": ape, "error": entry["error"]}  # fmt: skip

    def _keep(self, key: tuple[int, int, int, str], entry: dict[str, Any]) -> None:
        with self._lock:
            self._entries[key] = entry
            self._entries.move_to_end(key)
            while len(self._entries) > self.capacity:
                self._entries.popitem(last=False)


def session_ids_of(conn: Connection, graph: ViewGraph) -> dict[str, int]:
    """Return ``{name: id}`` of the sessions the graph's experiences belong to, in the graph's order."""
    return {name: session_id_by_name(conn=conn, name=name) for name in graph.session_names}


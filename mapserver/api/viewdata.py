"""What the web viewer draws: a map's graph as arrays, decimated on a grid for one viewport.

:class:`ViewCache` keeps, per map and keyed by the map's version (as :mod:`mapserver.api.graphs` does),
the experience poses, session and template of every experience and every link's ends, kind and
``active`` flag (a NULL flag reads as ``True``). :func:`decimate` answers a
viewport query: the experiences inside a bounding box, thinned to at most ``max_nodes`` by keeping one
experience per (grid cell, session) — the lowest id — on a square grid over the box, and the links
between the kept representatives of different cells (one per cell pair and kind). Everything is
vectorised numpy: a 100,000-experience map answers in milliseconds.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from core import LinkKind
from mapserver.bounds import MAX_QUERY_COORDINATE_M, value_problem
from mapserver.errors import InputError
from mapserver.formats import LINK_KIND_CODES
from mapserver.store import LINK_KIND_NAMES, Connection, Database, get_map
from mapserver.store.queries import map_version, view_experiences, view_links
from mapserver.store.sessions import session_names

View = Literal["xy", "xz"]
MAX_NODES = 50_000


@dataclass(frozen=True)
class ViewGraph:
    """A map's experience graph for drawing (one map version)."""

    map_id: int
    version: int
    poses: npt.NDArray[np.float64]  # (E, 4) x, y, z, yaw
    session: npt.NDArray[np.int64]  # (E,) index into ``session_names``
    template: npt.NDArray[np.int64]
    stamp: npt.NDArray[np.float64]
    session_names: list[str]
    link_from: npt.NDArray[np.int64]
    link_to: npt.NDArray[np.int64]
    link_kind: npt.NDArray[np.int64]  # index into LINK_KIND_NAMES
    link_active: npt.NDArray[np.bool_]
    link_dt: npt.NDArray[np.float64]
    link_distance: npt.NDArray[np.float64]

    def plane(self, view: View) -> npt.NDArray[np.float64]:
        """Return the (E, 2) drawing coordinates: x–y (top view) or x–z (side view)."""
        return self.poses[:, [0, 2]] if view == "xz" else self.poses[:, :2]


def load_view_graph(*, conn: Connection, map_id: int, version: int) -> ViewGraph:
    """Read a map's experiences and links (no templates, no engine state) into a :class:`ViewGraph`."""
    rows = view_experiences(conn=conn, map_id=map_id)
    exp = np.array(rows, dtype=np.float64).reshape(-1, 7)
    session_ids = exp[:, 4].astype(np.int64)
    uniq, codes = np.unique(session_ids, return_inverse=True)
    names = session_names(conn=conn, session_ids=uniq.tolist())
    links = view_links(conn=conn, map_id=map_id)
    arr = np.array([r[:4] for r in links], dtype=np.float64).reshape(-1, 4)
    kind = np.array([LINK_KIND_CODES.get(r[4], LinkKind.ODOMETRY) for r in links], dtype=np.int64)
    on = np.array([r[5] is None or bool(r[5]) for r in links], dtype=bool)
    return ViewGraph(
        map_id=map_id, version=version, poses=np.ascontiguousarray(exp[:, :4]), session=codes.astype(np.int64),
        template=exp[:, 5].astype(np.int64), stamp=exp[:, 6].copy(),
        session_names=[str(names.get(int(s), s)) for s in uniq.tolist()],
        link_from=arr[:, 0].astype(np.int64), link_to=arr[:, 1].astype(np.int64), link_kind=kind, link_active=on,
        link_dt=arr[:, 2].copy(), link_distance=arr[:, 3].copy(),
    )  # fmt: skip


class ViewCache:
    """Thread-safe LRU of :class:`ViewGraph` per map, reloaded when the map's version changes."""

    def __init__(self, db: Database, capacity: int = 4) -> None:
        self.db = db
        self.capacity = capacity
        self._entries: OrderedDict[int, ViewGraph] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, name: str) -> ViewGraph:
        """Return map ``name``'s current view graph (loaded again only after a write).

        Raises:
            UnknownMapError: no such map.
        """
        with self.db.read() as conn:
            found = map_version(conn=conn, name=name)
            if found is None:
                get_map(conn=conn, name=name)  # raises the 404 with the usual message
            map_id, version = found  # type: ignore[misc]
            with self._lock:
                entry = self._entries.get(map_id)
                if entry is not None and entry.version == version:
                    self._entries.move_to_end(map_id)
                    return entry
            entry = load_view_graph(conn=conn, map_id=map_id, version=version)
        with self._lock:
            self._entries[map_id] = entry
            self._entries.move_to_end(map_id)
            while len(self._entries) > self.capacity:
                self._entries.popitem(last=False)
        return entry


def parse_bbox(text: str | None) -> tuple[float, float, float, float] | None:
    """Parse ``"xmin,ymin,xmax,ymax"`` (None for no box).

    Raises:
        InputError: not four finite numbers within ±``MAX_QUERY_COORDINATE_M`` (1e12 m) with min < max.
    """
    if text is None or not text.strip():
        return None
    shown = text if len(text) <= 100 else text[:97] + "..."
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) == 4:
        for name, value in zip(("xmin", "ymin", "xmax", "ymax"), values, strict=True):
            problem = value_problem(value, MAX_QUERY_COORDINATE_M, "m")
            if problem is not None:
                msg = f"bbox {name} {problem}"
                raise InputError(msg)
    if len(values) != 4 or values[0] >= values[2] or values[1] >= values[3]:
        msg = f"bbox must be 'xmin,ymin,xmax,ymax' with xmin < xmax and ymin < ymax, got {shown!r}"
        raise InputError(msg)
    return values[0], values[1], values[2], values[3]


def bounds(xy: npt.NDArray[np.float64]) -> list[float]:
    """Return ``[xmin, ymin, xmax, ymax]`` of points (zeros for none)."""
    if xy.shape[0] == 0:
        return [0.0, 0.0, 0.0, 0.0]
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    return [float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])]


def _cells(graph: ViewGraph, pts: npt.NDArray[np.float64], sel: npt.NDArray[np.int64],
           box: tuple[float, ...], g: int) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], float]:
    """Return (first index of each occupied (cell, session), each point's group, cell size) on a g×g grid."""
    cell = max(box[2] - box[0], box[3] - box[1], 1e-9) / g
    cx = np.clip(((pts[:, 0] - box[0]) / cell).astype(np.int64), 0, g - 1)
    cy = np.clip(((pts[:, 1] - box[1]) / cell).astype(np.int64), 0, g - 1)
    key = (cy * g + cx) * (int(graph.session.max(initial=0)) + 1) + graph.session[sel]
    _uniq, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    return first, inverse.ravel(), cell


def _grid(
    graph: ViewGraph, pts: npt.NDArray[np.float64], sel: npt.NDArray[np.int64], box: tuple[float, ...],
    max_nodes: int, resolution: float,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], float]:
    """Return (kept ids, each selected point's representative, cell size): the finest grid within budget.

    The grid starts at g = ⌊√(max_nodes / S)⌋ cells a side (S sessions in view: a full box stays within
    the budget) and is refined by doubling g while the occupied (cell, session) groups stay within
    ``max_nodes`` and the cell is not finer than ``resolution`` (a sparse trajectory uses the budget).
    """
    sessions_in = int(np.unique(graph.session[sel]).size)
    g = max(1, math.isqrt(max(1, max_nodes // max(1, sessions_in))))
    first, inverse, cell = _cells(graph, pts, sel, box, g)
    for _ in range(6):
        finer = _cells(graph, pts, sel, box, 2 * g)
        if finer[0].size > max_nodes or finer[2] < resolution:
            break
        g, (first, inverse, cell) = 2 * g, finer
    kept = sel[first]  # sel is sorted by id, so the first of each group has the lowest id
    return kept, kept[inverse], cell


def decimate(
    graph: ViewGraph, *, bbox: tuple[float, float, float, float] | None, max_nodes: int, view: View = "xy",
    resolution: float = 0.0,
) -> dict[str, Any]:
    """Return the part of a map's graph inside ``bbox``, with at most ``max_nodes`` experiences.

    (At most max(``max_nodes``, S) for S sessions in the box: each session keeps at least one experience.)

    When the box holds more than ``max_nodes`` experiences, a g×g grid (g = ⌊√(max_nodes / S)⌋ for S
    sessions in the box, doubled while the occupied cells stay within budget and the cell stays coarser
    than ``resolution``, see :func:`_grid`) is laid over the box and each (cell, session) keeps its lowest-id
    experience; a
    link is kept between the representatives of its two ends' cells (one per cell pair and kind), so the
    drawing keeps the graph's shape at the zoom level's resolution. Links with an end outside the box are
    left out (the viewer asks for a box larger than the screen).

    Returns:
        ``{"nodes": {"id", "x", "y", "session"}, "links": {"a", "b", "kind", "active"}`` (a, b index the
        returned nodes), ``"in_view"`` (experiences in the box), ``"decimated"``, ``"cell"`` (grid cell
        size, 0 when not decimated), ``"bounds"`` (the whole map's), ``"sessions"``, ``"kinds"``, ``"ends"``
        (:func:`session_ends`)}.
    """
    xy = graph.plane(view)
    ids = np.arange(xy.shape[0], dtype=np.int64)
    box = bbox if bbox is not None else tuple(bounds(xy))
    inside = (xy[:, 0] >= box[0]) & (xy[:, 0] <= box[2]) & (xy[:, 1] >= box[1]) & (xy[:, 1] <= box[3])
    sel = ids[inside]
    in_view = int(sel.size)
    rep = np.full(xy.shape[0], -1, dtype=np.int64)  # experience -> representative experience (or -1)
    cell = 0.0
    decimated = in_view > max_nodes
    if decimated:
        kept, rep_sel, cell = _grid(graph, xy[sel], sel, box, max_nodes, resolution)
        rep[sel] = rep_sel
    else:
        kept = sel
        rep[sel] = sel
    order = np.full(xy.shape[0], -1, dtype=np.int64)
    order[kept] = np.arange(kept.size)
    a, b = rep[graph.link_from], rep[graph.link_to]
    ok = (a >= 0) & (b >= 0) & (a != b)
    la, lb = order[a[ok]], order[b[ok]]
    kind, active = graph.link_kind[ok], graph.link_active[ok]
    if decimated and la.size:
        lo, hi = np.minimum(la, lb), np.maximum(la, lb)
        n = np.int64(kept.size)
        lkey = (lo * n + hi) * 8 + kind * 2 + active.astype(np.int64)
        _u, first_link = np.unique(lkey, return_index=True)
        la, lb, kind, active = la[first_link], lb[first_link], kind[first_link], active[first_link]
    return {
        "nodes": {
            "id": kept.tolist(),
            "x": np.round(xy[kept, 0], 4).tolist(),
            "y": np.round(xy[kept, 1], 4).tolist(),
            "session": graph.session[kept].tolist(),
        },
        "links": {"a": la.tolist(), "b": lb.tolist(), "kind": kind.tolist(), "active": active.tolist()},
        "in_view": in_view,
        "total": int(xy.shape[0]),
        "decimated": bool(decimated),
        "cell": cell,
        "bounds": bounds(xy),
        "sessions": graph.session_names,
        "kinds": list(LINK_KIND_NAMES),
        "view": view,
        "ends": session_ends(graph, view),
    }


def session_ends(graph: ViewGraph, view: View = "xy") -> list[dict[str, Any]]:
    """Return where each session's trajectory starts and ends: its first and last experience by stamp.

    Taken over the whole map (not the box, not the decimated nodes), lowest id first among equal stamps:
    ``[{"session" (index into ``sessions``), "start": {"id", "x", "y"}, "end": {"id", "x", "y"}}]``.
    """
    if graph.session.size == 0:
        return []
    xy = graph.plane(view)
    ids = np.arange(graph.session.size, dtype=np.int64)
    order = np.lexsort((ids, graph.stamp, graph.session))  # by session, then stamp, then id
    ordered = graph.session[order]
    firsts = order[np.flatnonzero(np.diff(ordered, prepend=-1))]
    lasts = order[np.flatnonzero(np.diff(ordered, append=ordered[-1] + 1))]

    def point(k: int) -> dict[str, Any]:
        return {"id": k, "x": round(float(xy[k, 0]), 4), "y": round(float(xy[k, 1]), 4)}

    return [{"session": int(graph.session[a]), "start": point(int(a)), "end": point(int(b))}
            for a, b in zip(firsts.tolist(), lasts.tolist(), strict=True)]  # fmt: skip


def nearest(graph: ViewGraph, x: float, y: float, view: View = "xy") -> int | None:
    """Return the id of the experience nearest to (x, y) in the drawing plane (None for an empty map)."""
    xy = graph.plane(view)
    if xy.shape[0] == 0:
        return None
    d = (xy[:, 0] - x) ** 2 + (xy[:, 1] - y) ** 2
    return int(np.argmin(d))

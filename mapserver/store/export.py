"""Export a stored map: map JSON, TUM poses, PNG plot, g2o pose graph or CSV tables.

Map JSON is the contract's ``mapserver-map/1``; g2o is :mod:`mapserver.formats.g2o`; CSV is
:mod:`mapserver.formats.csv` (``--out X.csv`` holds the experiences, ``X.links.csv`` beside it the links).

JSON, TUM, g2o and CSV are written from :mod:`mapserver.store.streams` (rows read a batch at a time, the
same bytes as the formatters of a loaded map); the PNG plot is drawn on a figure of its own
(:mod:`mapserver.plotting`, no pyplot), so concurrent exports need no lock. Every writer is atomic
(temporary file + rename, :func:`mapserver.formats.atomic_write_chunks`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from sqlalchemy import case, select

from core import LinkKind
from core.se3 import quaternions_from_yaws
from mapserver.errors import InputError
from mapserver.formats import LINK_KIND_CODES, SessionInfo, atomic_write_bytes, atomic_write_chunks, map_json
from mapserver.plotting import add_segments, new_figure, png_bytes, session_colour
from mapserver.store.bulk import fetch_tuples
from mapserver.store.db import Database
from mapserver.store.maps import get_map
from mapserver.store.models import LINK_KIND_NAMES, Experience, Link
from mapserver.store.sessions import sessions_of_map
from mapserver.store.state import MapContent
from mapserver.store.streams import is_planar, open_export

__all__ = ["EXPORT_FORMATS", "PlotGraph", "export_map", "is_planar", "links_csv_path", "map_document", "render_png"]

ExportFormat = Literal["json", "tum", "png", "g2o", "csv"]
EXPORT_FORMATS: tuple[str, ...] = ("json", "tum", "png", "g2o", "csv")


def map_document(content: MapContent, *, odometry: np.ndarray | None = None) -> dict[str, Any]:
    """Return the map JSON document of a loaded map (sessions named, links with kinds).

    Args:
        content: a loaded map.
        odometry: optional (N, 4) ``[stamp, x, y, z]`` dead-reckoning rows (the ``odometry`` extension).
    """
    meta = content.meta
    return map_json(
        params=content.params,
        snapshot=content.snapshot,
        sessions=[SessionInfo(s.name, s.log_sha256, s.frames_processed) for s in meta.sessions],
        session_name_by_origin=meta.session_names(),
        odometry=odometry,
    )


def tum_rows(snapshot: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return experience (stamps, positions (E, 3), quaternions (E, 4)) in stamp order (stable)."""
    pose = np.asarray(snapshot["em_pose"], dtype=np.float64).reshape(-1, 4)
    stamps = np.asarray(snapshot["em_stamp"], dtype=np.float64).reshape(-1)
    order = np.argsort(stamps, kind="stable")
    return stamps[order], pose[order, :3], quaternions_from_yaws(pose[order, 3])


@dataclass(frozen=True)
class PlotGraph:
    """What the PNG plot draws: experience positions by session, links by kind and status."""

    name: str
    xy: np.ndarray  # (E, 2)
    origin: np.ndarray  # (E,) session id of each experience
    sessions: list[tuple[int, str]]  # (id, name) in creation order
    src: np.ndarray  # (K,)
    dst: np.ndarray  # (K,)
    kinds: np.ndarray  # (K,) em_link_kind codes
    active: np.ndarray  # (K,) bool


def plot_graph_of(content: MapContent) -> PlotGraph:
    """Return the plot data of a loaded map."""
    snap = content.snapshot
    src = np.asarray(snap["em_link_from"]).reshape(-1)
    active = np.ones(src.shape[0], dtype=bool)
    given = np.asarray(snap.get("em_link_active", active), dtype=bool).reshape(-1)
    active[: given.size] = given[: src.shape[0]]
    return PlotGraph(
        name=content.meta.map.name, xy=np.asarray(snap["em_pose"]).reshape(-1, 4)[:, :2],
        origin=np.asarray(snap["em_origin"]).reshape(-1), sessions=[(s.id, s.name) for s in content.meta.sessions],
        src=src, dst=np.asarray(snap["em_link_to"]).reshape(-1), kinds=np.asarray(snap["em_link_kind"]).reshape(-1),
        active=active,
    )  # fmt: skip


def read_plot_graph(db: Database, *, name: str) -> PlotGraph:
    """Read the plot data of stored map ``name`` from its rows alone (no templates, no engine state).

    Raises:
        UnknownMapError: no such map.
    """
    kind_code = case(LINK_KIND_CODES, value=Link.kind, else_=-1)
    with db.read() as conn:
        record = get_map(conn=conn, name=name)
        experiences = np.array(
            fetch_tuples(conn, select(Experience.x, Experience.y, Experience.session_id)
                         .where(Experience.map_id == record.id).order_by(Experience.local_id)),
            dtype=np.float64,
        ).reshape(-1, 3)  # fmt: skip
        links = np.array(
            fetch_tuples(conn, select(Link.from_id, Link.to_id, kind_code, Link.active)
                         .where(Link.map_id == record.id).order_by(Link.seq)),
            dtype=np.int64,
        ).reshape(-1, 4)  # fmt: skip
        sessions = [(s.id, s.name) for s in sessions_of_map(conn=conn, map_id=record.id)]
    return PlotGraph(
        name=record.name, xy=experiences[:, :2], origin=experiences[:, 2].astype(np.int64), sessions=sessions,
        src=links[:, 0], dst=links[:, 1], kinds=links[:, 2], active=links[:, 3].astype(bool),
    )  # fmt: skip


def render_png(content: MapContent | PlotGraph, *, title: str | None = None) -> bytes:
    """Plot the experience graph (x, y), coloured by session, links drawn by kind; return PNG bytes.

    Draws on a figure of its own (:mod:`mapserver.plotting`: no pyplot state), so any number of threads may
    render at once.
    """
    graph = content if isinstance(content, PlotGraph) else plot_graph_of(content)
    xy, src, dst, kinds, active = graph.xy, graph.src, graph.dst, graph.kinds, graph.active
    fig = new_figure((8.0, 8.0))
    ax = fig.subplots()
    styles = {LinkKind.ODOMETRY: ("0.6", "-"), LinkKind.LOOP: ("tab:red", "--"), LinkKind.MERGE: ("tab:green", "-"),
              LinkKind.MANUAL: ("tab:purple", ":")}  # fmt: skip
    for kind, (colour, style) in styles.items():
        chosen = (kinds == kind) & active
        label = LINK_KIND_NAMES[kind]
        if np.any(chosen):
            segments = np.stack([xy[src[chosen]], xy[dst[chosen]]], axis=1)
            add_segments(ax, segments, colors=colour, linestyles=style, linewidths=0.8, label=f"{label} links")
    if not active.all():  # switched off by robust relaxation: grey, dashed
        segments = np.stack([xy[src[~active]], xy[dst[~active]]], axis=1)
        add_segments(ax, segments, colors="0.75", linestyles="--", linewidths=0.8, label="switched-off links")
    for k, (session_id, session_name) in enumerate(graph.sessions):
        chosen = graph.origin == session_id
        if np.any(chosen):
            ax.scatter(xy[chosen, 0], xy[chosen, 1], s=10, color=session_colour(k), label=session_name, zorder=3)
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or f"{graph.name}: {xy.shape[0]} experiences, {src.shape[0]} links")
    if xy.shape[0] or src.shape[0]:
        ax.legend(loc="best", fontsize="small")
    ax.grid(True, linewidth=0.3)
    return png_bytes(fig)


def links_csv_path(out: str | Path) -> Path:
    """Return where ``export --format csv --out OUT`` writes the links table: ``OUT``'s stem + ``.links.csv``."""
    target = Path(out)
    return target.with_name(f"{target.stem if target.suffix.lower() == '.csv' else target.name}.links.csv")


def export_map(db: Database, *, name: str, fmt: str, out: str | Path) -> dict[str, Any]:
    """Write stored map ``name`` to ``out`` as ``json``, ``tum``, ``png``, ``g2o`` or ``csv``; return a summary.

    JSON, TUM, g2o and CSV are written while the rows are read (:mod:`mapserver.store.streams`: one batch in
    memory); the PNG plot reads the graph's rows only. The JSON carries the ``odometry`` extension when the
    map has exactly one session with dead-reckoning rows (what ``evaluate`` uses for its odometry baseline).

    Raises:
        InputError: unknown format, or the output directory does not exist.
        UnknownMapError: no such map.
        ConflictError: JSON of a map holding an infinite number.
    """
    if fmt not in EXPORT_FORMATS:
        msg = f"unknown export format {fmt!r}; choose one of {', '.join(EXPORT_FORMATS)}"
        raise InputError(msg)
    target = Path(out)
    if not target.parent.is_dir():
        msg = f"output directory does not exist: {str(target.parent)!r}"
        raise InputError(msg)
    result: dict[str, Any] = {"map": name, "format": fmt, "out": str(target)}
    if fmt == "png":
        graph = read_plot_graph(db, name=name)
        atomic_write_bytes(target, render_png(graph))
        return {**result, "experiences": int(graph.xy.shape[0])}
    stream = open_export(db, name=name, fmt=fmt)
    try:
        atomic_write_chunks(target, stream)
    finally:
        stream.close()
    if fmt == "csv":
        links = open_export(db, name=name, fmt="links.csv")
        try:
            atomic_write_chunks(links_csv_path(target), links)
        finally:
            links.close()
        result["links_out"] = str(links_csv_path(target))
    return {**result, "experiences": stream.head.experiences}

"""Export a stored map: map JSON, TUM poses, PNG plot, g2o pose graph or CSV tables.

Map JSON is the contract's ``mapserver-map/1``; g2o is :mod:`mapserver.formats_g2o`; CSV is
:mod:`mapserver.formats_csv` (``--out X.csv`` holds the experiences, ``X.links.csv`` beside it the links).

Every writer is atomic (temporary file + rename, :func:`mapserver.formats.atomic_write_bytes`).
"""

from __future__ import annotations

import io
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mapserver.errors import InputError
from mapserver.formats import SessionInfo, atomic_write_bytes, map_json, write_map_json, write_tum
from mapserver.formats_csv import experiences_csv, links_csv
from mapserver.formats_g2o import g2o_text
from mapserver.store.db import Database
from mapserver.store.mapio import load_map
from mapserver.store.sessions import get_reckoning
from mapserver.store.state import MapContent

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
    half = 0.5 * pose[order, 3]
    quats = np.zeros((order.shape[0], 4))
    quats[:, 2] = np.sin(half)
    quats[:, 3] = np.cos(half)
    return stamps[order], pose[order, :3], quats


def render_png(content: MapContent, *, title: str | None = None) -> bytes:
    """Plot the experience graph (x, y), coloured by session, links drawn by kind; return PNG bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    snap = content.snapshot
    pose = np.asarray(snap["em_pose"]).reshape(-1, 4)
    origin = np.asarray(snap["em_origin"]).reshape(-1)
    src = np.asarray(snap["em_link_from"]).reshape(-1)
    dst = np.asarray(snap["em_link_to"]).reshape(-1)
    kinds = np.asarray(snap["em_link_kind"]).reshape(-1)
    active = np.ones(src.shape[0], dtype=bool)
    active[: np.asarray(snap.get("em_link_active", active)).size] = np.asarray(snap.get("em_link_active", active))
    fig, ax = plt.subplots(figsize=(8, 8), dpi=100)
    styles = {0: ("0.6", "-", "odometry"), 1: ("tab:red", "--", "loop"), 2: ("tab:green", "-", "merge"),
              3: ("tab:purple", ":", "manual")}  # fmt: skip
    for code, (colour, style, label) in styles.items():
        chosen = (kinds == code) & active
        if np.any(chosen):
            segments = np.stack([pose[src[chosen], :2], pose[dst[chosen], :2]], axis=1)
            ax.add_collection(
                LineCollection(segments, colors=colour, linestyles=style, linewidths=0.8, label=f"{label} links")
            )
    if not active.all():  # switched off by robust relaxation: grey, dashed
        segments = np.stack([pose[src[~active], :2], pose[dst[~active], :2]], axis=1)
        ax.add_collection(
            LineCollection(segments, colors="0.75", linestyles="--", linewidths=0.8, label="switched-off links")
        )
    cmap = plt.get_cmap("tab10")
    for k, session in enumerate(content.meta.sessions):
        chosen = origin == session.id
        if np.any(chosen):
            ax.scatter(pose[chosen, 0], pose[chosen, 1], s=10, color=cmap(k % 10), label=session.name, zorder=3)
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or f"{content.meta.map.name}: {pose.shape[0]} experiences, {src.shape[0]} links")
    if pose.shape[0] or src.shape[0]:
        ax.legend(loc="best", fontsize="small")
    ax.grid(True, linewidth=0.3)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    plt.close(fig)
    return buffer.getvalue()


def links_csv_path(out: str | Path) -> Path:
    """Return where ``export --format csv --out OUT`` writes the links table: ``OUT``'s stem + ``.links.csv``."""
    target = Path(out)
    return target.with_name(f"{target.stem if target.suffix.lower() == '.csv' else target.name}.links.csv")


def is_planar(params: Mapping[str, Any]) -> bool:
    """True for maps of a 3-DoF (x, y, θ) lattice (``pc_dim_z`` ≤ 1): exported as SE2."""
    return int(params.get("pc_dim_z", 1)) <= 1


def export_map(db: Database, *, name: str, fmt: str, out: str | Path) -> dict[str, Any]:
    """Write stored map ``name`` to ``out`` as ``json``, ``tum``, ``png``, ``g2o`` or ``csv``; return a summary.

    The JSON carries the ``odometry`` extension when the map has exactly one session with dead-reckoning
    rows (what ``evaluate`` uses for its odometry baseline).

    Raises:
        InputError: unknown format, or the output directory does not exist.
        UnknownMapError: no such map.
    """
    if fmt not in EXPORT_FORMATS:
        msg = f"unknown export format {fmt!r}; choose one of {', '.join(EXPORT_FORMATS)}"
        raise InputError(msg)
    target = Path(out)
    if not target.parent.is_dir():
        msg = f"output directory does not exist: {str(target.parent)!r}"
        raise InputError(msg)
    content = load_map(db, name=name)
    if fmt == "json":
        odometry = None
        if len(content.meta.sessions) == 1:
            with db.read() as conn:
                rows, _pose = get_reckoning(conn=conn, session_id=content.meta.sessions[0].id)
            odometry = rows if rows.shape[0] else None
        write_map_json(target, map_document(content, odometry=odometry))
    elif fmt == "tum":
        stamps, positions, quats = tum_rows(content.snapshot)
        write_tum(target, stamps, positions, quats)
    elif fmt == "g2o":
        atomic_write_bytes(target, g2o_text(content.snapshot, planar=is_planar(content.params)).encode("utf-8"))
    elif fmt == "csv":
        names = content.meta.session_names()
        atomic_write_bytes(target, experiences_csv(content.snapshot, names).encode("utf-8"))
        atomic_write_bytes(links_csv_path(target), links_csv(content.snapshot).encode("utf-8"))
    else:
        atomic_write_bytes(target, render_png(content))
    result = {
        "map": name,
        "format": fmt,
        "out": str(target),
        "experiences": int(np.asarray(content.snapshot["em_pose"]).reshape(-1, 4).shape[0]),
    }
    if fmt == "csv":
        result["links_out"] = str(links_csv_path(target))
    return result

"""Mission reports: one self-contained HTML page (PNGs embedded, and written beside it) of a map or a session.

A report holds:

* the experience map drawn to scale, coloured by session, links by kind (odometry, loop, merge, switched
  off), with each merge's matched places marked (the experiences that stand for each identified
  template pair, in both sessions);
* the activation timeline (OpenRatSLAM2 Fig. 6): template id against time for every frame, *new* (the
  frame created its template) or *recognised* (it matched a stored one), from the session's stored
  timeline (``sessions.activations``: each frame's template by its stable identity, resolved to the map's
  ids now); and experience id against time. Sessions stored before the timeline existed get one point
  per experience instead (its template new when no earlier experience used it);
* per session with ground truth, the trajectory against ground truth and the APE/Hausdorff figures of
  :func:`mapserver.evaluation.evaluate_map`. Ground truth comes from a TUM file given by the caller, the
  ground-truth topic of a log given by the caller, or the log the server stored for the session's upload.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mapserver.errors import InputError, NotFoundError
from mapserver.evaluation import evaluate_map, plot_map_vs_ground_truth
from mapserver.formats import Trajectory, atomic_write_bytes, odometry_trajectory
from mapserver.plotting import add_segments, new_figure, png_bytes
from mapserver.statuses import MergeStatus
from mapserver.store import Connection, Database, find_map, get_map_by_id, load_map
from mapserver.store.export import map_document
from mapserver.store.identities import template_ids_by_identity, template_ids_matching
from mapserver.store.jobs import last_done_upload
from mapserver.store.merge_events import MergeEventRecord, list_merge_events
from mapserver.store.sessions import SessionRecord, find_session_map, get_activations, get_reckoning

COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22")
LINK_STYLE = {"odometry": ("#9e9e9e", "-"), "loop": ("#d62728", "-"), "merge": ("#6a1b9a", "--"),
              "manual": ("#00838f", ":")}  # fmt: skip


@dataclass
class ReportInputs:
    """Everything a report is drawn from (read once from the store)."""

    map_name: str
    session: str | None
    doc: dict[str, Any]
    events: list[MergeEventRecord]
    merge_places: list[list[int]]
    ground_truth: dict[str, Trajectory] = field(default_factory=dict)
    odometry: dict[str, Trajectory] = field(default_factory=dict)
    #: per session with a stored timeline: (N, 2) ``[stamp, template id in this map]`` per frame (−1: none)
    #: and (N,) whether the frame created its template
    activations: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)


def resolve_target(db: Database, name: str) -> tuple[str, str | None]:
    """Return ``(map name, session name or None)`` for a map's or a session's name.

    Raises:
        NotFoundError: neither a map nor a session has that name, or the session belongs to no map.
    """
    with db.read() as conn:
        record = find_map(conn=conn, name=name)
        if record is not None:
            return record.name, None
        row = find_session_map(conn=conn, name=name)
        if row is None:
            msg = f"no map or session named {name!r}"
            raise NotFoundError(msg)
        if row[1] is None:
            msg = f"session {name!r} belongs to no map (it was merged away or its map was dropped)"
            raise NotFoundError(msg)
        return get_map_by_id(conn=conn, map_id=row[1]).name, row[0]


def _template_places(db: Database, map_id: int, events: list[MergeEventRecord]) -> list[list[int]]:
    """Return, per identified template pair of the map's applied merges, the experiences using it today."""
    uids = [tuple(p["target_uid"]) for e in events if e.status == MergeStatus.APPLIED
            for p in (e.matches or {}).get("templates", []) if "target_uid" in p]  # fmt: skip
    if not uids:
        return []
    with db.read() as conn:
        ids = template_ids_matching(
            conn=conn, map_id=map_id, session_ids=[u[0] for u in uids], origin_indices=[u[1] for u in uids]
        )
    return [[i] for i in ids]  # template ids; experiences are looked up from the document


def stored_log(db: Database, session: str) -> Path | None:
    """Return the uploaded log the server kept for a session (None when there is none on disk)."""
    with db.read() as conn:
        upload = last_done_upload(conn=conn, session_name=session)
    if upload is None:
        return None
    path = Path(upload)
    return path if path.exists() else None


def log_ground_truth(path: Path) -> Trajectory | None:
    """Return the ground-truth topic of a mission log as a trajectory (None when it has none)."""
    from mapserver.ingest.reader import open_log

    with open_log(path) as log:
        samples = list(log.ground_truth())
    if not samples:
        return None
    stamps = np.array([s.stamp_ns for s in samples], dtype=np.float64) * 1e-9
    xyz = np.array([[s.x, s.y, s.z] for s in samples], dtype=np.float64)
    quat = np.array([[s.qx, s.qy, s.qz, s.qw] for s in samples], dtype=np.float64)
    return Trajectory(stamps, xyz, quat)


def gather(
    db: Database, name: str, *, ground_truth: dict[str | None, Trajectory] | None = None,
    logs: dict[str | None, Path] | None = None,
) -> ReportInputs:  # fmt: skip
    """Read what a report of map or session ``name`` needs: the map document, merges, ground truth, odometry.

    ``ground_truth`` and ``logs`` are keyed by session name (``None``: the report's session, or the map's
    only session). Sessions with neither get the ground truth of the log the server kept for them, if any.

    Raises:
        NotFoundError: no such map or session.
        InputError: a key names no session of the map.
    """
    map_name, session = resolve_target(db, name)
    content = load_map(db, name=map_name)
    names = [s.name for s in content.meta.sessions]
    doc = map_document(content)
    with db.read() as conn:
        record = find_map(conn=conn, name=map_name)
        assert record is not None
        events = [e for e in list_merge_events(conn=conn) if e.map_id == record.id]
        odometry: dict[str, Trajectory] = {}
        for s in content.meta.sessions:
            rows, _pose = get_reckoning(conn=conn, session_id=s.id)
            odo = odometry_trajectory({"odometry": rows.tolist()}) if rows.shape[0] else None
            if odo is not None:
                odometry[s.name] = odo
        activations = _activations(conn, record.id, content.meta.sessions)
    default = session or (names[0] if len(names) == 1 else None)
    truth: dict[str, Trajectory] = {}
    sources: list[tuple[str | None, Trajectory | Path]] = [*(ground_truth or {}).items(), *(logs or {}).items()]
    for key, source in sources:
        who = key if key is not None else default
        if who is None or who not in names:
            msg = f"ground truth for {key or '(unnamed)'!r}: name one of the map's sessions ({', '.join(names)})"
            raise InputError(msg)
        found = source if isinstance(source, Trajectory) else log_ground_truth(Path(source))
        if found is not None and who not in truth:
            truth[who] = found
    for who in [session] if session else names:
        if who not in truth and (kept := stored_log(db, who)) is not None and (found := log_ground_truth(kept)):
            truth[who] = found
    places = _template_places(db, record.id, events)
    return ReportInputs(map_name, session, doc, events, places, truth, odometry, activations)


def _activations(
    conn: Connection, map_id: int, sessions: Sequence[SessionRecord]
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Return each session's stored per-frame timeline with template identities resolved to this map's ids.

    A frame's template is named by its stable identity (origin session, origin index); merges renumber
    templates, the ``templates`` table says what each identity is called in the map now.
    """
    ids = template_ids_by_identity(conn=conn, map_id=map_id)
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for s in sessions:
        stored = get_activations(conn=conn, session_id=s.id)
        if stored is None or stored.shape[0] == 0:
            continue
        local = np.array([ids.get((int(a), int(b)), -1) for a, b in stored[:, 1:3]], dtype=np.float64)
        out[s.name] = (np.column_stack([stored[:, 0], local]), stored[:, 3] > 0)
    return out


def map_figure(inputs: ReportInputs) -> bytes:
    """Draw the experience map (top view, to scale): sessions in colours, links by kind, merge places marked."""
    doc = inputs.doc
    exps = doc["experiences"]
    xy = np.array([[e["x"], e["y"]] for e in exps], dtype=np.float64).reshape(-1, 2)
    sessions = [s["name"] for s in doc["sessions"]]
    who = np.array([sessions.index(e["session"]) if e["session"] in sessions else 0 for e in exps], dtype=np.int64)
    fig = new_figure((8.0, 7.0))
    ax = fig.add_subplot(1, 1, 1)
    for kind, (colour, style) in LINK_STYLE.items():
        segs = [(xy[lk["from"]], xy[lk["to"]]) for lk in doc["links"] if lk["kind"] == kind and lk.get("active", True)]
        if segs:
            add_segments(ax, segs, colors=colour, linestyles=style, linewidths=1.0, label=kind)
    off = [(xy[lk["from"]], xy[lk["to"]]) for lk in doc["links"] if not lk.get("active", True)]
    if off:
        add_segments(ax, off, colors="#bbbbbb", linestyles=":", linewidths=1.0, label="switched off")
    for k, name in enumerate(sessions):
        mine = who == k
        if inputs.session is None or inputs.session == name:
            ax.scatter(xy[mine, 0], xy[mine, 1], s=10, color=COLOURS[k % len(COLOURS)], zorder=3, label=name)
        else:
            ax.scatter(xy[mine, 0], xy[mine, 1], s=6, color="#d0d0d0", zorder=2, label=f"{name} (other session)")
    templates = np.array([e["template"] for e in exps], dtype=np.int64)
    marked = np.isin(templates, [p[0] for p in inputs.merge_places])
    if marked.any():
        ax.scatter(xy[marked, 0], xy[marked, 1], s=120, facecolors="none", edgecolors="#e91e63", linewidths=1.5,
                   zorder=4, label="merge: matched places")  # fmt: skip
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(f"map {inputs.map_name}: {len(exps)} experiences, {len(doc['links'])} links")
    fig.tight_layout()
    return png_bytes(fig)


def timeline(inputs: ReportInputs) -> dict[str, Any]:
    """Return the activation timeline's series: per experience its stamp, template and new/recognised flag.

    An experience's template is *new* when no earlier experience (by stamp) used it, *recognised* otherwise.
    Restricted to the report's session when it has one (a template first seen in another session is then
    recognised: the session found a place the map knew).
    """
    exps = sorted(inputs.doc["experiences"], key=lambda e: (e["stamp"], e["id"]))
    stamps = np.array([e["stamp"] for e in exps], dtype=np.float64)
    templates = np.array([e["template"] for e in exps], dtype=np.int64)
    _u, first = np.unique(templates, return_index=True)
    new = np.zeros(templates.size, dtype=bool)
    new[first] = True
    keep = np.array([inputs.session is None or e["session"] == inputs.session for e in exps], dtype=bool)
    ids = np.array([e["id"] for e in exps], dtype=np.int64)
    sessions = [e["session"] for e in exps]
    return {"stamp": stamps[keep], "template": templates[keep], "new": new[keep], "id": ids[keep],
            "session": [s for s, k in zip(sessions, keep, strict=True) if k]}  # fmt: skip


def timeline_figure(inputs: ReportInputs) -> bytes:
    """Draw template id and experience id against mission time (OpenRatSLAM2 Fig. 6), new vs recognised.

    Time runs from each session's first experience (sessions are recorded at different times); sessions are
    told apart by colour, new templates by filled dots and recognised ones by crosses.
    """
    series = timeline(inputs)
    sessions = [s["name"] for s in inputs.doc["sessions"]]
    who = np.array([sessions.index(s) if s in sessions else 0 for s in series["session"]], dtype=np.int64)
    t = series["stamp"].copy()
    for k in np.unique(who):
        t[who == k] -= t[who == k].min()
    fig = new_figure((9.0, 6.5))
    ax = fig.add_subplot(2, 1, 1)
    ax2 = fig.add_subplot(2, 1, 2, sharex=ax)
    new = series["new"]
    for k in np.unique(who).tolist():
        mine, colour, name = who == k, COLOURS[k % len(COLOURS)], sessions[k]
        if name in inputs.activations:  # every frame (stored timeline): the active template, new or recognised
            frames, created = inputs.activations[name]
            ft, ftemplate = frames[:, 0] - float(series["stamp"][mine].min()), frames[:, 1]
            shown = ftemplate >= 0
            ax.scatter(ft[shown & created], ftemplate[shown & created], s=12, color=colour,
                       label=f"{name}: new template ({int((shown & created).sum())} frames)")  # fmt: skip
            recognised = shown & ~created
            ax.scatter(ft[recognised], ftemplate[recognised], s=14, marker="x", color=colour, linewidths=0.7,
                       label=f"{name}: recognised ({int(recognised.sum())} frames)")  # fmt: skip
        else:  # stored before the timeline existed: one point per experience
            ax.scatter(t[mine & new], series["template"][mine & new], s=12, color=colour,
                       label=f"{name}: new template ({int((mine & new).sum())})")  # fmt: skip
            ax.scatter(t[mine & ~new], series["template"][mine & ~new], s=30, marker="x", color=colour,
                       label=f"{name}: recognised ({int((mine & ~new).sum())})")  # fmt: skip
        ax2.plot(t[mine], series["id"][mine], ".", color=colour, markersize=4, label=f"{name}: experience created")
    stamp_of = {e["id"]: e["stamp"] for e in inputs.doc["experiences"]}
    start = {sessions[k]: float(series["stamp"][who == k].min()) for k in np.unique(who).tolist()}
    session_of = {e["id"]: e["session"] for e in inputs.doc["experiences"]}
    closures = [lk for lk in inputs.doc["links"] if lk["kind"] in ("loop", "merge")]
    for n, lk in enumerate(closures):
        later = max((lk["from"], lk["to"]), key=lambda i: stamp_of[i])
        if session_of[later] not in start:
            continue
        ax2.axvline(stamp_of[later] - start[session_of[later]], color="#6a1b9a" if lk["kind"] == "merge" else "#d62728",
                    lw=0.8, alpha=0.6, label="loop / merge closure" if n == 0 else None)  # fmt: skip
    ax.set_ylabel("template id")
    ax.legend(loc="best", fontsize=7)
    ax.grid(True, alpha=0.3)
    ax2.set_xlabel("time since the session's first experience (s)")
    ax2.set_ylabel("experience id")
    ax2.legend(loc="best", fontsize=7)
    ax2.grid(True, alpha=0.3)
    fig.suptitle(f"activation timeline: {inputs.session or inputs.map_name}")
    fig.tight_layout()
    return png_bytes(fig)


def _table(rows: list[tuple[str, Any]]) -> str:
    cells = "".join(f"<tr><th>{html.escape(str(k))}</th><td>{html.escape(str(v))}</td></tr>" for k, v in rows)
    return f"<table>{cells}</table>"


def _img(name: str, data: bytes, alt: str) -> str:
    b64 = base64.b64encode(data).decode("ascii")
    image = f'<img src="data:image/png;base64,{b64}" alt="{html.escape(alt)}">'
    return f"<figure>{image}<figcaption>{html.escape(name)}: {html.escape(alt)}</figcaption></figure>"


def _fmt(value: Any) -> str:
    return "–" if value is None else f"{value:.3f}" if isinstance(value, float) else str(value)


def write_report(inputs: ReportInputs, out: Path) -> dict[str, Any]:
    """Write ``report.html`` and its PNGs into ``out``; return ``{"report", "pngs", "evaluation"}``.

    Raises:
        InputError: ``out`` exists and is not a directory.
    """
    if out.exists() and not out.is_dir():
        msg = f"--out {str(out)!r} exists and is not a directory"
        raise InputError(msg)
    out.mkdir(parents=True, exist_ok=True)
    doc = inputs.doc
    pngs: dict[str, bytes] = {"map.png": map_figure(inputs), "timeline.png": timeline_figure(inputs)}
    evaluation: dict[str, Any] = {}
    for session, gt in sorted(inputs.ground_truth.items()):
        odo = inputs.odometry.get(session)
        try:
            evaluation[session] = evaluate_map(doc, gt, odometry=odo, session=session)
            target = out / f"ground_truth_{len(evaluation)}.png"
            plot_map_vs_ground_truth(doc, gt, target, odometry=odo, session=session)
            pngs[target.name] = target.read_bytes()
        except InputError as err:
            evaluation[session] = {"error": str(err)}
    for name, data in pngs.items():
        atomic_write_bytes(out / name, data)
    kinds = {k: sum(1 for lk in doc["links"] if lk["kind"] == k) for k in LINK_STYLE}
    off = sum(1 for lk in doc["links"] if not lk.get("active", True))
    series = timeline(inputs)
    summary = [("map", inputs.map_name), ("report of", inputs.session or "the whole map"),
               ("sessions", ", ".join(s["name"] for s in doc["sessions"])),
               ("experiences", len(series["id"])), ("templates", doc["templates"]),
               ("new / recognised experiences", f"{int(series['new'].sum())} / {int((~series['new']).sum())}"),
               *((f"{k} links", v) for k, v in kinds.items()), ("switched-off links", off),
               ("merge events", len(inputs.events))]  # fmt: skip
    parts = [f"<h1>Mission report: {html.escape(inputs.session or inputs.map_name)}</h1>", _table(summary)]
    parts.append("<h2>Accuracy against ground truth</h2>")
    if evaluation:
        for session, ev in evaluation.items():
            keys = ("ape_rmse", "odometry_ape_rmse", "hausdorff", "experiences", "aligned", "ape_max", "error")
            figures = [(k, _fmt(ev[k])) for k in keys if k in ev]
            figures += [(f"RPE per {r['delta_m']:g} m (translation, rotation °, segments)",
                      f"{_fmt(r['trans_rmse'])}, {_fmt(r['rot_rmse_deg'])}, {r['pairs']}")
                     for r in ev.get("rpe", [])]  # fmt: skip
            parts.append(f"<h3>{html.escape(session)}</h3>" + _table(figures))
    else:
        parts.append("<p>No ground truth: give <code>--ground-truth</code> or <code>--log</code> (a log with a "
                     "ground-truth topic), or process the log through the server, which keeps it.</p>")  # fmt: skip
    parts.append("<h2>Merges</h2>")
    rows = "".join(
        f"<tr><td>{e.id}</td><td>{e.status}</td><td>{e.mode}</td><td>{e.confirmations}</td>"
        f"<td>{', '.join(f'{t:.3f}' for t in e.transform[:3])}</td><td>{np.degrees(e.yaw):.1f}°</td>"
        f"<td>{len((e.matches or {}).get('templates', []))}</td></tr>"
        for e in inputs.events
    )
    parts.append("<table><tr><th>event</th><th>status</th><th>mode</th><th>confirmations</th><th>t (m)</th>"
                 f"<th>yaw</th><th>matched templates</th></tr>{rows}</table>")  # fmt: skip
    parts.append("<h2>Figures</h2>")
    captions = {"map.png": "experience map: loop closures and merges (matched places circled)",
                "timeline.png": "template and experience activation timeline (one point per experience)"}  # fmt: skip
    parts.extend(_img(name, data, captions.get(name, "trajectory against ground truth")) for name, data in pngs.items())
    page = (
        "<!doctype html><html lang='en'><head><meta charset='utf-8'>"
        f"<title>report {html.escape(inputs.session or inputs.map_name)}</title><style>"
        "body{font:14px system-ui,sans-serif;margin:2em;max-width:1000px}table{border-collapse:collapse;margin:.5em 0}"
        "th,td{border:1px solid #ddd;padding:.2em .6em;text-align:left}img{max-width:100%}</style></head><body>"
        + "\n".join(parts) + "</body></html>"
    )  # fmt: skip
    report = out / "report.html"
    atomic_write_bytes(report, page.encode("utf-8"))
    return {"report": str(report), "pngs": [str(out / n) for n in pngs], "evaluation": evaluation}

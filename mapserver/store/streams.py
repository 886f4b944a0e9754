"""Stored maps written while they are read: map JSON, TUM, CSV and g2o in bounded memory.

:func:`open_export` begins one read transaction, reads the map's head (parameters, sessions, counts, whether
its links carry a status, the negative-zero patches of its float rows) and returns an :class:`ExportStream`:
an iterator of byte chunks that reads the experiences and links ``batch`` rows at a time
(:func:`mapserver.store.bulk.iter_tuples`: a server-side cursor on PostgreSQL) and formats each batch.
Memory is one batch, whatever the map's size.

The bytes are those the formatters of a loaded map write (``formats.write_map_json(map_document(...))``,
``formats.write_tum``, ``formats_csv``, ``formats_g2o``): the same key order, separators and float
text, the same numpy arithmetic per row (quaternions, information matrices), and ``-0.0`` restored from
the state's patches as :func:`mapserver.store.state.read_map_state` restores it.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Callable, Iterator, Mapping
from contextlib import ExitStack
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
from sqlalchemy import Connection, func, select

from core.se3 import quaternions_from_yaws
from mapserver.errors import ConflictError, InputError
from mapserver.formats import MAP_FORMAT, TUM_HEADER, _plain
from mapserver.formats.csv import EXPERIENCE_COLUMNS, LINK_COLUMNS
from mapserver.formats.g2o import edge_lines, manual_lines, vertex_lines
from mapserver.store.bulk import iter_tuples
from mapserver.store.db import Database, small_page_cache
from mapserver.store.errors import CorruptStateError
from mapserver.store.maps import get_map
from mapserver.store.models import Experience, Link, MapState
from mapserver.store.sessions import SessionRecord, get_reckoning, sessions_of_map
from mapserver.store.state import NEGZERO_PREFIX

BATCH_ROWS = 1000
STREAM_FORMATS: tuple[str, ...] = ("json", "tum", "csv", "links.csv", "g2o")
"""``csv`` is the experiences table, ``links.csv`` the links table (``formats_csv``)."""

_PATCHED = ("em_pose", "em_stamp", "em_link_transform", "em_link_dt", "em_link_distance")
_dumps = partial(json.dumps, ensure_ascii=False, allow_nan=False, separators=(",", ":"))
_EXPERIENCE_ROW = (Experience.local_id, Experience.x, Experience.y, Experience.z, Experience.yaw,
                   Experience.template, Experience.stamp, Experience.session_id)  # fmt: skip
_LINK_ROW = (Link.from_id, Link.to_id, Link.dx, Link.dy, Link.dz, Link.dyaw, Link.dt, Link.distance, Link.kind,
             Link.active)  # fmt: skip


@dataclass(frozen=True)
class ExportHead:
    """What an export reads before its rows.

    Attributes:
        map_id: the map's id.
        name: its name.
        params: its effective parameters.
        sessions: its sessions in creation order.
        templates: its template count (the map JSON's ``templates``).
        experiences: its experience count.
        link_status: its state carries ``em_link_active`` (map JSON ``"active": false``, CSV ``active``).
        negzero: per float row key, the flat indices of its ``-0.0`` values.
    """

    map_id: int
    name: str
    params: dict[str, Any]
    sessions: tuple[SessionRecord, ...]
    templates: int
    experiences: int
    link_status: bool
    negzero: dict[str, np.ndarray]

    @property
    def session_names(self) -> dict[int, str]:
        """Session id → name."""
        return {s.id: s.name for s in self.sessions}


def read_export_head(conn: Connection, name: str) -> ExportHead:
    """Return the head of map ``name`` (see :class:`ExportHead`).

    Raises:
        UnknownMapError: no such map.
        CorruptStateError: the map has no stored state.
    """
    record = get_map(conn=conn, name=name)
    state = conn.execute(
        select(MapState.manifest, MapState.arrays, MapState.n_experiences).where(MapState.map_id == record.id)
    ).first()
    if state is None:
        msg = f"map {record.name!r} has no stored state"
        raise CorruptStateError(msg)
    manifest: dict[str, Any] = dict(state[0])
    counted = manifest.get("lv_means") or manifest.get("lv_templates") or {"shape": [0]}
    wanted = {NEGZERO_PREFIX + key for key in _PATCHED}
    with np.load(io.BytesIO(state[1]), allow_pickle=False) as archive:
        negzero = {k[len(NEGZERO_PREFIX) :]: np.asarray(archive[k]) for k in archive.files if k in wanted}
    return ExportHead(
        map_id=record.id, name=record.name, params=dict(record.params),
        sessions=tuple(sessions_of_map(conn=conn, map_id=record.id)), templates=int(counted["shape"][0]),
        experiences=int(state[2]), link_status="em_link_active" in manifest, negzero=negzero,
    )  # fmt: skip


class ExportStream:
    """A map being exported: iterate it for byte chunks; exhausting or closing it ends its read transaction."""

    def __init__(self, stack: ExitStack, head: ExportHead, chunks: Iterator[bytes]) -> None:
        self._stack = stack
        self.head = head
        self._chunks = chunks
        self._closed = False

    def __iter__(self) -> ExportStream:
        return self

    def __next__(self) -> bytes:
        """Return the next chunk (a few hundred kB at most)."""
        try:
            return next(self._chunks)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """End the export: close its cursor and its read transaction (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            close = getattr(self._chunks, "close", None)
            if close is not None:
                close()
        finally:
            self._stack.close()


def open_export(db: Database, *, name: str, fmt: str, batch: int = BATCH_ROWS) -> ExportStream:
    """Begin exporting stored map ``name`` as ``fmt`` (one of :data:`STREAM_FORMATS`).

    Everything that can refuse the export is checked here, before the first chunk: the map exists, and
    (JSON) it holds no non-finite number.

    Raises:
        InputError: unknown format.
        UnknownMapError: no such map.
        ConflictError: JSON of a map holding an infinite number (JSON has none; TUM, CSV and g2o write ``inf``).
    """
    writer = _WRITERS.get(fmt)
    if writer is None:
        msg = f"unknown export format {fmt!r}; choose one of {', '.join(STREAM_FORMATS)}"
        raise InputError(msg)
    stack = ExitStack()
    try:
        conn = stack.enter_context(db.read())
        stack.enter_context(small_page_cache(conn))
        head = read_export_head(conn, name)
        chunks = writer(conn, head, batch)
    except BaseException:
        stack.close()
        raise
    return ExportStream(stack, head, chunks)


# ------------------------------------------------------------------------------------------------ rows


def _experience_batches(conn: Connection, head: ExportHead, batch: int, *, by_stamp: bool = False) -> Iterator[Any]:
    """Yield experiences as (ids (n,), pose (n, 4) x y z yaw, templates, stamps (n,), sessions) per batch."""
    order = (Experience.stamp, Experience.local_id) if by_stamp else (Experience.local_id,)
    statement = select(*_EXPERIENCE_ROW).where(Experience.map_id == head.map_id).order_by(*order)
    for rows in iter_tuples(conn, statement, batch):
        ids = np.fromiter((r[0] for r in rows), dtype=np.int64, count=len(rows))
        pose = np.array([r[1:5] for r in rows], dtype=np.float64).reshape(-1, 4)
        stamps = np.fromiter((r[6] for r in rows), dtype=np.float64, count=len(rows))
        _restore_negative_zeros(pose, ids, head.negzero.get("em_pose"))
        _restore_negative_zeros(stamps.reshape(-1, 1), ids, head.negzero.get("em_stamp"))
        yield ids, pose, [int(r[5]) for r in rows], stamps, [int(r[7]) for r in rows]


def _link_batches(conn: Connection, head: ExportHead, batch: int) -> Iterator[Any]:
    """Yield links as (from, to, transform (n, 4), dt, distance, kinds, active) per batch, in link order."""
    statement = select(Link.seq, *_LINK_ROW).where(Link.map_id == head.map_id).order_by(Link.seq)
    for rows in iter_tuples(conn, statement, batch):
        seq = np.fromiter((r[0] for r in rows), dtype=np.int64, count=len(rows))
        tf = np.array([r[3:7] for r in rows], dtype=np.float64).reshape(-1, 4)
        dt = np.fromiter((r[7] for r in rows), dtype=np.float64, count=len(rows))
        distance = np.fromiter((r[8] for r in rows), dtype=np.float64, count=len(rows))
        _restore_negative_zeros(tf, seq, head.negzero.get("em_link_transform"))
        _restore_negative_zeros(dt.reshape(-1, 1), seq, head.negzero.get("em_link_dt"))
        _restore_negative_zeros(distance.reshape(-1, 1), seq, head.negzero.get("em_link_distance"))
        yield ([int(r[1]) for r in rows], [int(r[2]) for r in rows], tf, dt, distance, [str(r[9]) for r in rows],
               [bool(r[10]) for r in rows])  # fmt: skip


def _restore_negative_zeros(values: np.ndarray, ids: np.ndarray, patch: np.ndarray | None) -> None:
    """Set the ``-0.0`` of rows ``ids`` of a float row key (flat ``patch`` indices over its columns) in place."""
    if patch is None or patch.size == 0 or ids.size == 0:
        return
    rows, cols = np.divmod(np.asarray(patch, dtype=np.int64), values.shape[1])
    hit = np.isin(rows, ids)
    if not hit.any():
        return
    where = {int(i): k for k, i in enumerate(ids.tolist())}
    for row, col in zip(rows[hit].tolist(), cols[hit].tolist(), strict=True):
        values[where[row], col] = -0.0


def _halves(yaw: np.ndarray) -> tuple[list[float], list[float]]:
    """Return the z and w components of each yaw's quaternion (:func:`core.se3.quaternions_from_yaws`)."""
    quaternions = quaternions_from_yaws(yaw)
    return quaternions[:, 2].tolist(), quaternions[:, 3].tolist()


# ------------------------------------------------------------------------------------------------ formats


def _map_json(conn: Connection, head: ExportHead, batch: int) -> Iterator[bytes]:
    """Map JSON (``mapserver-map/1``) as ``formats.write_map_json(map_document(...))`` writes it."""
    odometry = _odometry(conn, head)
    _check_finite(conn, head, odometry)
    return _map_json_chunks(conn, head, batch, odometry)


def _map_json_chunks(conn: Connection, head: ExportHead, batch: int, odometry: np.ndarray | None) -> Iterator[bytes]:
    sessions = [{"name": str(s.name), "log_sha256": str(s.log_sha256), "frames": int(s.frames_processed)}
                for s in head.sessions]  # fmt: skip
    yield (
        f'{{"format":{_dumps(MAP_FORMAT)},"params":{_dumps(_plain(head.params))},"sessions":{_dumps(sessions)},'
        f'"templates":{head.templates},"experiences":['
    ).encode()
    names, first = head.session_names, True
    for ids, pose, templates, stamps, origins in _experience_batches(conn, head, batch):
        qz, qw = _halves(pose[:, 3])
        items = [
            {"id": i, "x": p[0], "y": p[1], "z": p[2], "qx": 0.0, "qy": 0.0, "qz": z, "qw": w, "yaw": p[3],
             "template": t, "stamp": s, "session": names.get(o)}
            for i, p, z, w, t, s, o in zip(ids.tolist(), pose.tolist(), qz, qw, templates, stamps.tolist(), origins,
                                           strict=True)
        ]  # fmt: skip
        yield (("" if first else ",") + _dumps(items)[1:-1]).encode("utf-8")
        first = False
    yield b'],"links":['
    first = True
    for src, dst, tf, dt, distance, kinds, active in _link_batches(conn, head, batch):
        items = []
        for s, t, m, d, dist, kind, on in zip(src, dst, tf.tolist(), dt.tolist(), distance.tolist(), kinds, active,
                                              strict=True):  # fmt: skip
            item: dict[str, Any] = {"from": s, "to": t, "dt": d, "distance": dist, "kind": kind, "transform": m}
            if head.link_status and not on:
                item["active"] = False
            items.append(item)
        yield (("" if first else ",") + _dumps(items)[1:-1]).encode("utf-8")
        first = False
    yield b"]"
    if odometry is not None:
        yield b',"odometry":['
        for k in range(0, odometry.shape[0], batch):
            yield (("," if k else "") + _dumps(odometry[k : k + batch].tolist())[1:-1]).encode("utf-8")
        yield b"]"
    yield b"}\n"


def _odometry(conn: Connection, head: ExportHead) -> np.ndarray | None:
    """Return the ``odometry`` extension: the dead reckoning of a map of exactly one session, if it has rows."""
    if len(head.sessions) != 1:
        return None
    rows, _pose = get_reckoning(conn=conn, session_id=head.sessions[0].id)
    return rows if rows.shape[0] else None


def _check_finite(conn: Connection, head: ExportHead, odometry: np.ndarray | None) -> None:
    """Refuse JSON of a map with an infinite (or NaN) number: JSON cannot carry one."""
    columns: dict[type[Experience] | type[Link], tuple[Any, ...]] = {
        Experience: (Experience.x, Experience.y, Experience.z, Experience.yaw, Experience.stamp),
        Link: (Link.dx, Link.dy, Link.dz, Link.dyaw, Link.dt, Link.distance),
    }
    largest = [
        value
        for table, cols in columns.items()
        for value in conn.execute(
            select(*(func.max(func.abs(c)) for c in cols)).where(table.map_id == head.map_id)
        ).one()
    ]
    finite = all(v is None or math.isfinite(float(v)) for v in largest)
    if not finite or (odometry is not None and not np.isfinite(odometry).all()):
        msg = (
            f"map {head.name!r} holds a non-finite number (an infinite pose, stamp or link value), which JSON "
            "cannot carry; export it as tum, csv or g2o"
        )
        raise ConflictError(msg)


def _tum(conn: Connection, head: ExportHead, batch: int) -> Iterator[bytes]:
    """TUM experience poses in stamp order (stable) as ``formats.write_tum`` writes them."""
    yield (TUM_HEADER + "\n").encode("utf-8")
    for _ids, pose, _templates, stamps, _origins in _experience_batches(conn, head, batch, by_stamp=True):
        qz, qw = _halves(pose[:, 3])
        lines = [
            f"{t:.9f} " + " ".join(f"{v:.17g}" for v in (p[0], p[1], p[2], 0.0, 0.0, z, w))
            for t, p, z, w in zip(stamps.tolist(), pose.tolist(), qz, qw, strict=True)
        ]
        yield ("\n".join(lines) + "\n").encode("utf-8")


def _csv_text(rows: list[list[object]], header: tuple[str, ...] | None = None) -> bytes:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\r\n")
    if header is not None:
        writer.writerow(header)
    writer.writerows(rows)
    return buffer.getvalue().encode("utf-8")


def _experiences_csv(conn: Connection, head: ExportHead, batch: int) -> Iterator[bytes]:
    """The experiences table as ``formats_csv.experiences_csv`` writes it."""
    yield _csv_text([], EXPERIENCE_COLUMNS)
    names = head.session_names
    for ids, pose, templates, stamps, origins in _experience_batches(conn, head, batch):
        qz, qw = _halves(pose[:, 3])
        rows: list[list[object]] = [
            [i, names.get(o, ""), t, s, *p, 0.0, 0.0, z, w]
            for i, o, t, s, p, z, w in zip(ids.tolist(), origins, templates, stamps.tolist(), pose.tolist(), qz, qw,
                                           strict=True)
        ]  # fmt: skip
        yield _csv_text(rows)


def _links_csv(conn: Connection, head: ExportHead, batch: int) -> Iterator[bytes]:
    """The links table as ``formats_csv.links_csv`` writes it (``active`` when the state carries link status)."""
    yield _csv_text([], (*LINK_COLUMNS, "active") if head.link_status else LINK_COLUMNS)
    for src, dst, tf, dt, distance, kinds, active in _link_batches(conn, head, batch):
        rows: list[list[object]] = [
            [s, t, kind, d, dist, *m] + (["true" if on else "false"] if head.link_status else [])
            for s, t, kind, d, dist, m, on in zip(src, dst, kinds, dt.tolist(), distance.tolist(), tf.tolist(), active,
                                                  strict=True)
        ]  # fmt: skip
        yield _csv_text(rows)


def _numbers(values: np.ndarray) -> list[str]:
    return [" ".join(repr(float(v)) for v in row) for row in values.tolist()]


def is_planar(params: Mapping[str, Any]) -> bool:
    """True for maps of a 3-DoF (x, y, θ) lattice (``pc_dim_z`` ≤ 1): exported as SE2."""
    return int(params.get("pc_dim_z", 1)) <= 1


def _g2o(conn: Connection, head: ExportHead, batch: int) -> Iterator[bytes]:
    """The experience graph as ``formats_g2o.g2o_text`` writes it (SE2 for planar maps, else SE3:QUAT).

    Vertices, then the active links, ``FIX 0``, the switched-off links as comments (a second pass over the links,
    so that memory stays one batch), and last the manual links named as comments ``# manual FROM TO``.
    """
    planar = is_planar(head.params)
    any_line = False
    for ids, pose, _templates, _stamps, _origins in _experience_batches(conn, head, batch):
        yield "".join(vertex_lines(ids, pose, planar=planar)).encode("utf-8")
        any_line = True
    for inactive in (False, True):
        if inactive and head.experiences:
            yield b"FIX 0\n"
        for src, dst, tf, _dt, distance, _kinds, active in _link_batches(conn, head, batch):
            chosen = ~np.asarray(active, dtype=bool) if inactive else np.asarray(active, dtype=bool)
            if chosen.any():
                lines = edge_lines(np.asarray(src)[chosen], np.asarray(dst)[chosen], tf[chosen], distance[chosen],
                                   planar=planar, inactive=inactive)  # fmt: skip
                yield "".join(lines).encode("utf-8")
                any_line = True
    manual = select(Link.from_id, Link.to_id).where(Link.map_id == head.map_id, Link.kind == "manual")
    for rows in iter_tuples(conn, manual.order_by(Link.seq), batch):
        yield "".join(manual_lines([r[0] for r in rows], [r[1] for r in rows])).encode("utf-8")
    if not any_line:
        yield b"\n"


_WRITERS: dict[str, Callable[[Connection, ExportHead, int], Iterator[bytes]]] = {
    "json": _map_json,
    "tum": _tum,
    "csv": _experiences_csv,
    "links.csv": _links_csv,
    "g2o": _g2o,
}

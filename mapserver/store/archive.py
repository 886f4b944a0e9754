"""Archived map states: freeze a map's state (before a merge) and restore it exactly (unmerge, redo).

An archive row (``map_archives``) holds one compressed npz: the full engine snapshot (origins as
session ids), the stable identities of its templates and experiences, and the map's session ids.
Template pixels are *not* copied when the template is already stored as a ``templates`` row with the
same identity, shape and mean (templates are immutable): the archive keeps a reference and the row's
blob is reused on restore. Template rows are never deleted while their session exists, so references
stay valid. ``sdr-htm`` view cells are the exception: a merge re-expresses a view cell's prototype in the
stored map's cortex and the store rewrites its row (``state_templates.rewrite_reexpressed_templates``), often at the
same size (its "mean"), so their archives keep every prototype inline (a few hundred bytes each).

Unmerge recipe (what ``mapserver unmerge`` does, issue 5)::

    with db.write() as conn:
        event = get_merge_event(conn=conn, event_id=...)
        restore_map_states(conn=conn, archive_ids=event.archive_ids)   # every map as it was
        set_merge_status(conn=conn, event_id=event.id, status=MergeStatus.UNDONE)

Restoring several archives in one call is order-independent: every map named by an archive is emptied
first, so identities the merged map held are free again when the pre-merge maps are written back.

An archive may also keep its sessions' progress rows (:class:`~mapserver.store.sessions.SessionProgress`:
status, frames, dead reckoning, activation timeline), written back exactly with :func:`restore_progress`
(an unmerge archives the merged map that way, role ``merged``, so that a redo gives it back bit for bit).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

import numpy as np
import numpy.typing as npt
from sqlalchemy import Connection, delete, insert, select

from mapserver.errors import NotFoundError, StoreError
from mapserver.store.arrays import pack_npz, unpack_npz
from mapserver.store.blobs import resolve_arrays, share_arrays
from mapserver.store.bulk import fetch_tuples
from mapserver.store.maps import clear_map, create_map, find_map, get_map_by_id
from mapserver.store.models import MapArchive, Template
from mapserver.store.sessions import SessionProgress, set_session_progress
from mapserver.store.state import WriteResult, frontend_of, plain_params, read_map_state, write_map_state

_META = "__archive__."
_TEMPLATE_REF = _META + "template_ref"
_TEMPLATE_INLINE = _META + "template_inline"
_TEMPLATE_SHAPE = _META + "template_shape"
_IDENTITIES = ("template_session", "template_index", "experience_session", "experience_index")
_PROGRESS = _META + "progress"


@dataclass(frozen=True)
class ArchivedState:
    """A map state read back from an archive (``load_archive``)."""

    id: int
    event_id: int | None
    role: str | None
    map_id: int | None
    map_name: str
    map_version: int | None
    params: dict[str, Any]
    session_ids: tuple[int, ...]
    snapshot: dict[str, np.ndarray]
    template_session: npt.NDArray[np.int64]
    template_index: npt.NDArray[np.int64]
    experience_session: npt.NDArray[np.int64]
    experience_index: npt.NDArray[np.int64]
    created_at: datetime
    progress: tuple[SessionProgress, ...] = ()


def _template_refs(
    conn: Connection, sessions: np.ndarray, indices: np.ndarray, means: np.ndarray, shape: tuple[int, int]
) -> np.ndarray:
    """Return a bool mask: True where the template is stored as a row with the same identity, shape and mean."""
    n = sessions.shape[0]
    if n == 0:
        return np.zeros(0, dtype=bool)
    rows = conn.execute(
        select(Template.session_id, Template.origin_index, Template.height, Template.width, Template.mean).where(
            Template.session_id.in_(np.unique(sessions).tolist())
        )
    ).all()
    stored = {(int(r[0]), int(r[1])): (int(r[2]), int(r[3]), float(r[4])) for r in rows}
    mask = np.zeros(n, dtype=bool)
    for i, (s, k, m) in enumerate(zip(sessions.tolist(), indices.tolist(), means.tolist(), strict=True)):
        hit = stored.get((s, k))
        mask[i] = hit is not None and hit[0] == shape[0] and hit[1] == shape[1] and hit[2] == m
    return mask


def archive_state(
    *,
    conn: Connection,
    map_name: str,
    params: Any,
    snapshot: Mapping[str, npt.ArrayLike],
    session_ids: Sequence[int],
    template_session: npt.ArrayLike,
    template_index: npt.ArrayLike,
    experience_session: npt.ArrayLike,
    experience_index: npt.ArrayLike,
    map_id: int | None = None,
    map_version: int | None = None,
    event_id: int | None = None,
    role: str | None = None,
    progress: Sequence[SessionProgress] = (),
) -> int:
    """Archive an in-memory map state (e.g. a new session's partial map at the moment it merges).

    Args:
        conn: a connection in a write transaction.
        map_name: the name the state is restored under.
        params: the engine parameters (``core.Params`` or its dict).
        snapshot: the engine snapshot; ``lv_origin``/``em_origin`` must be session ids.
        session_ids: the state's sessions.
        template_session: (N,) origin session of each template.
        template_index: (N,) index of each template within its session.
        experience_session: (E,) origin session of each experience.
        experience_index: (E,) index of each experience within its session.
        map_id: the map the state belonged to, if stored.
        map_version: that map's version when archived.
        event_id: the merge event the archive belongs to.
        role: its role in that event (``target``, ``source``, or ``merged``: ``merge_events.MERGED_ARCHIVE_ROLE``).
        progress: session rows' progress to keep with the state (see :func:`restore_progress`).

    Returns:
        The archive id.

    Raises:
        StoreError: the identities do not match the snapshot's sizes.
    """
    arrays = {key: np.asarray(value) for key, value in snapshot.items()}
    templates = _snapshot_templates(arrays)
    ids = _checked_identities(arrays, templates, template_session, template_index, experience_session, experience_index)
    content = _archive_content(conn, arrays, templates, ids, reference=frontend_of(params) != "sdr-htm")
    content.update(_progress_arrays(progress))
    row = {
        "event_id": event_id,
        "role": role,
        "map_id": map_id,
        "map_name": map_name,
        "map_version": map_version,
        "params": plain_params(params),
        "session_ids": [int(s) for s in session_ids],
        "n_templates": int(templates.shape[0]),
        "n_experiences": int(ids["experience_index"].shape[0]),  # checked against the snapshot's experiences
        "n_links": int(np.asarray(arrays.get("em_link_from", np.zeros(0))).reshape(-1).shape[0]),
        "state": pack_npz(share_arrays(conn, content)),
    }
    return int(conn.execute(insert(MapArchive).values(**row).returning(MapArchive.id)).scalar_one())


def _snapshot_templates(arrays: Mapping[str, np.ndarray]) -> np.ndarray:
    """Return the snapshot's (N, ty, tx) templates.

    Raises:
        StoreError: the snapshot has no 3-D ``lv_templates``.
    """
    templates = arrays.get("lv_templates")
    if templates is None or templates.ndim != 3:
        msg = "the snapshot to archive lacks float32 (N, ty, tx) lv_templates"
        raise StoreError(msg)
    return templates


def _checked_identities(
    arrays: Mapping[str, np.ndarray],
    templates: np.ndarray,
    template_session: npt.ArrayLike,
    template_index: npt.ArrayLike,
    experience_session: npt.ArrayLike,
    experience_index: npt.ArrayLike,
) -> dict[str, npt.NDArray[np.int64]]:
    """Return the templates' and experiences' identities as flat int64 arrays, keyed as in ``_IDENTITIES``.

    Raises:
        StoreError: the identities do not match the snapshot's sizes.
    """
    ids = {
        "template_session": np.asarray(template_session, dtype=np.int64).reshape(-1),
        "template_index": np.asarray(template_index, dtype=np.int64).reshape(-1),
        "experience_session": np.asarray(experience_session, dtype=np.int64).reshape(-1),
        "experience_index": np.asarray(experience_index, dtype=np.int64).reshape(-1),
    }
    n = templates.shape[0]
    e = np.asarray(arrays.get("em_pose", np.zeros((0, 4)))).reshape(-1, 4).shape[0]
    for key, value in ids.items():
        if value.shape[0] != (n if key.startswith("template") else e):
            msg = f"{key} has {value.shape[0]} entries for {n} templates and {e} experiences"
            raise StoreError(msg)
    return ids


def _archive_content(
    conn: Connection,
    arrays: Mapping[str, np.ndarray],
    templates: np.ndarray,
    ids: Mapping[str, npt.NDArray[np.int64]],
    *,
    reference: bool = True,
) -> dict[str, np.ndarray]:
    """Return the arrays the archive's npz holds: the snapshot with only unreferenced templates inline, and ids.

    ``reference``: templates stored as rows are referenced (False: every template inline; mutable rows).
    """
    n = templates.shape[0]
    means = np.asarray(arrays.get("lv_means", np.zeros(n)), dtype=np.float64).reshape(-1)
    referenced = np.zeros(n, dtype=bool)
    if reference:
        referenced = _template_refs(conn, ids["template_session"], ids["template_index"], means, templates.shape[1:])
    content = {k: v for k, v in arrays.items() if k != "lv_templates"}
    content[_META + "keys"] = np.asarray(list(arrays), dtype=str)
    content["__lv_templates_inline"] = np.ascontiguousarray(templates[~referenced])
    content[_TEMPLATE_INLINE] = ~referenced
    content[_TEMPLATE_SHAPE] = np.asarray(templates.shape, dtype=np.int64)
    content[_META + "template_dtype"] = np.asarray(templates.dtype.str)
    for key, value in ids.items():
        content[_META + key] = value
    return content


def _progress_arrays(progress: Sequence[SessionProgress]) -> dict[str, np.ndarray]:
    """Return the npz entries that keep sessions' progress rows: scalars as JSON, blobs as bytes."""
    if not progress:
        return {}
    scalars = [{"session": p.session_id, "status": p.status, "frames": p.frames_processed,
                "last_stamp": p.last_stamp, "pose": p.reckoning_pose,
                "finished_at": None if p.finished_at is None else p.finished_at.isoformat(),
                "reckoning": p.reckoning is not None, "activations": p.activations is not None}
               for p in progress]  # fmt: skip
    out = {_PROGRESS: np.asarray(json.dumps(scalars))}
    for k, p in enumerate(progress):
        for key, blob in (("reckoning", p.reckoning), ("activations", p.activations)):
            if blob is not None:
                out[f"{_PROGRESS}.{k}.{key}"] = np.frombuffer(blob, dtype=np.uint8)
    return out


def _progress_from(content: dict[str, np.ndarray]) -> tuple[SessionProgress, ...]:
    """Return (and take out of ``content``) the sessions' progress rows an archive keeps."""
    if _PROGRESS not in content:
        return ()
    scalars = json.loads(str(content.pop(_PROGRESS)))
    out = []
    for k, s in enumerate(scalars):
        blobs = {key: content.pop(f"{_PROGRESS}.{k}.{key}").tobytes() if s[key] else None
                 for key in ("reckoning", "activations")}  # fmt: skip
        out.append(SessionProgress(
            session_id=int(s["session"]), status=str(s["status"]), frames_processed=int(s["frames"]),
            last_stamp=s["last_stamp"], reckoning=blobs["reckoning"], reckoning_pose=s["pose"],
            activations=blobs["activations"],
            finished_at=None if s["finished_at"] is None else datetime.fromisoformat(s["finished_at"]),
        ))  # fmt: skip
    return tuple(out)


def restore_progress(*, conn: Connection, archived: ArchivedState) -> None:
    """Write the sessions' progress rows an archive keeps back exactly (status, frames, reckoning, timeline)."""
    for progress in archived.progress:
        set_session_progress(conn=conn, progress=progress)


def delete_archive(*, conn: Connection, archive_id: int) -> None:
    """Delete one archive row (a redo drops the ``merged`` archive it restored: the map is live again)."""
    conn.execute(delete(MapArchive).where(MapArchive.id == archive_id))


def archive_map_state(
    *, conn: Connection, map_id: int, event_id: int | None = None, role: str | None = None,
    progress: Sequence[SessionProgress] = (),
) -> int:  # fmt: skip
    """Archive a stored map's current state (call it before a merge changes or drops the map).

    ``progress``: session rows' progress to keep with it (an unmerge keeps the merged map's sessions').

    Returns:
        The archive id.
    """
    content = read_map_state(conn=conn, map_id=map_id)
    meta = content.meta
    return archive_state(
        conn=conn,
        map_name=meta.map.name,
        params=content.params,
        snapshot=content.snapshot,
        session_ids=[s.id for s in meta.sessions],
        template_session=meta.template_session,
        template_index=meta.template_index,
        experience_session=meta.experience_session,
        experience_index=meta.experience_index,
        map_id=map_id,
        map_version=meta.map.version,
        event_id=event_id,
        role=role,
        progress=progress,
    )


def load_archive(*, conn: Connection, archive_id: int) -> ArchivedState:
    """Read an archived state back, templates included (referenced ones from their rows), exactly.

    Raises:
        NotFoundError: no such archive.
        StoreError: a referenced template row is missing.
    """
    row = conn.execute(
        select(
            MapArchive.event_id, MapArchive.role, MapArchive.map_id, MapArchive.map_name, MapArchive.map_version,
            MapArchive.params, MapArchive.session_ids, MapArchive.state, MapArchive.created_at,
        ).where(MapArchive.id == archive_id)
    ).first()  # fmt: skip
    if row is None:
        msg = f"no archived map state with id {archive_id!r}"
        raise NotFoundError(msg)
    content = resolve_arrays(conn, unpack_npz(row[7]), f"archive {archive_id}")
    progress = _progress_from(content)
    keys = [str(k) for k in content.pop(_META + "keys")]
    ids = {key: content.pop(_META + key).astype(np.int64) for key in _IDENTITIES}
    inline_mask = content.pop(_TEMPLATE_INLINE).astype(bool)
    shape = tuple(int(v) for v in content.pop(_TEMPLATE_SHAPE))
    dtype = np.dtype(str(content.pop(_META + "template_dtype")))
    inline = content.pop("__lv_templates_inline")
    templates = np.empty(shape, dtype=dtype)
    templates[inline_mask] = inline
    wanted = np.flatnonzero(~inline_mask)
    if wanted.size:
        sessions = ids["template_session"][wanted]
        indices = ids["template_index"][wanted]
        stored = {}
        for s in np.unique(sessions).tolist():
            rows = fetch_tuples(
                conn,
                select(Template.origin_index, Template.data).where(Template.session_id == s),
            )
            stored.update({(s, int(k)): data for k, data in rows})
        for j, (s, k) in zip(wanted.tolist(), zip(sessions.tolist(), indices.tolist(), strict=True), strict=True):
            data = stored.get((s, k))
            if data is None:
                msg = f"archive {archive_id}: template (session {s}, index {k}) is no longer stored"
                raise StoreError(msg)
            templates[j] = np.frombuffer(data, dtype="<f4").reshape(shape[1:]).astype(dtype)
    content["lv_templates"] = templates
    snapshot = {key: content[key] for key in keys}
    return ArchivedState(
        id=archive_id,
        event_id=row[0],
        role=row[1],
        map_id=row[2],
        map_name=str(row[3]),
        map_version=row[4],
        params=dict(row[5]),
        session_ids=tuple(int(s) for s in row[6]),
        snapshot=snapshot,
        created_at=row[8],
        progress=progress,
        **ids,
    )


@dataclass(frozen=True)
class ArchiveHead:
    """An archive's name, role and sessions, read without its state."""

    id: int
    map_name: str
    role: str | None
    session_ids: tuple[int, ...]


def archive_head(*, conn: Connection, archive_id: int) -> ArchiveHead:
    """Return an archive's name, role and sessions without reading (or unpacking) its state.

    Raises:
        NotFoundError: no such archive.
    """
    row = conn.execute(
        select(MapArchive.map_name, MapArchive.role, MapArchive.session_ids).where(MapArchive.id == archive_id)
    ).first()
    if row is None:
        msg = f"no archived map state with id {archive_id!r}"
        raise NotFoundError(msg)
    return ArchiveHead(archive_id, str(row[0]), row[1], tuple(int(s) for s in row[2]))


def restore_map_states(
    *, conn: Connection, archive_ids: Sequence[int], names: Mapping[int, str] | None = None
) -> list[WriteResult]:
    """Write archived states back as stored maps, each under its archived name, in one transaction.

    ``names``: archive id → the name to restore it under instead (a map renamed since, a session moved out).
    Every map named by an archive is emptied first (created if it no longer exists), then each state is
    written with its archived sessions and identities; the maps' versions are bumped. Maps not named by
    an archive are not touched, so an identity still held by one of them is an ``OwnershipError``.

    Returns:
        One write result per archive, in the given order.

    Raises:
        NotFoundError: an archive id is unknown.
        OwnershipError: another map still holds a template or experience of an archived state.
    """
    states = [load_archive(conn=conn, archive_id=a) for a in archive_ids]
    targets: list[tuple[int, int]] = []
    for archived in states:
        name = (names or {}).get(archived.id, archived.map_name)
        record = find_map(conn=conn, name=name)
        if record is None:
            record = create_map(conn=conn, name=name, params=archived.params)
        else:
            clear_map(conn=conn, map_id=record.id)
        targets.append((record.id, record.version))
    results = []
    for archived, (map_id, _version) in zip(states, targets, strict=True):
        version = get_map_by_id(conn=conn, map_id=map_id).version
        results.append(
            write_map_state(
                conn=conn,
                map_id=map_id,
                expected_version=version,
                params=archived.params,
                snapshot=archived.snapshot,
                session_ids=list(archived.session_ids),
                template_index=archived.template_index,
                experience_index=archived.experience_index,
            )
        )
    return results

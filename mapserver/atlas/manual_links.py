"""Manual links: an operator joins two experiences as the same place, or with a stated transform.

For revisits that views never match (opposite directions, night and day), as RTAB-Map's database viewer
lets its users add constraints by hand. ``mapserver link`` and ``POST /v1/maps/{name}/links`` call
:func:`link_experiences`.

* One map: the link (kind ``manual``) is added to the map's experience graph and the map settles
  (:meth:`core.experience_map.ExperienceMap.settle`), robust check included: a manual link is switchable
  like a loop closure (:data:`core.links.SWITCHABLE_KINDS`), so one that contradicts the map is switched off
  (stored with ``active`` false, counted by the map's health) and reported as such, never bent into the map.
* Two maps: linking experience ``from`` of map A to experience ``to`` of map B merges B into A through that
  link: B's poses are placed by the SE(3) transform that puts ``to`` at ``from`` ⊕ the stated transform
  (:func:`mapserver.merge.merge_snapshots` with a match that identifies no template: the views differ), the
  link joins the two graphs, and the merged map settles. The merged map keeps the oldest map's name, as every
  merge does (:mod:`mapserver.atlas`).

Either way the link is a merge event (mode ``manual``) with the archives of the maps as they were, its
author and its time: ``mapserver unmerge`` / ``POST /v1/merges/{id}/undo`` restores them bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core import Engine, LinkKind
from core.angles import wrap_angle
from core.se3 import compose, inverse, relative
from mapserver.atlas import (
    ID_NEXT_KEY,
    AtlasMap,
    MergeToWrite,
    PartialSide,
    get_map_by_id_or_stale,
    read_atlas_map,
    write_merges,
)
from mapserver.bounds import MAX_ANGLE_RAD, MAX_POSITION_M
from mapserver.errors import ConflictError, InputError, MergeError, NotFoundError
from mapserver.merge import Match, StoredMap, merge_snapshots
from mapserver.merge.identity import RowIdentities
from mapserver.merge.provenance import match_to_dict, record_summary
from mapserver.store import Connection, Database, get_map
from mapserver.store.archive import archive_map_state
from mapserver.store.merge_events import MergeEventSpec, record_merge_event
from mapserver.store.sessions import get_sessions
from mapserver.store.state import write_map_state

MANUAL_MODE = "manual"
"""The ``mode`` of a manual link's merge event."""

MAX_AUTHOR_CHARS = 200
"""The longest author name a link keeps."""

IDENTITY_7 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True)
class LinkRequest:
    """A manual link to add.

    Attributes:
        map_name: the map of experience ``from_id`` (map A).
        from_id: an experience of map A.
        to_id: an experience of ``to_map`` (map A itself when it is None).
        to_map: map B, merged into A through the link; None: the link stays within map A.
        transform: the pose of ``to`` in ``from``'s frame, (dx, dy, dz, dyaw) in metres and radians (all
            zero: the same place, facing the same way).
        author: who added it (the token's label or id for the REST API; ``--author`` or the OS user for the CLI).
    """

    map_name: str
    from_id: int
    to_id: int
    to_map: str | None = None
    transform: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    author: str = ""


@dataclass(frozen=True)
class LinkOutcome:
    """What a manual link did: its event, the map that holds it, whether the robust check kept it on.

    ``from_id``/``to_id``/``link`` are ids in ``map_name`` as it is after the link. ``misfit_m`` and
    ``misfit_rad``: how far the settled map puts ``to`` from where the link says (0 for a link kept on in a
    map that agrees with it; the contradiction itself for a link switched off). ``checked``: False when the map's
    parameters switch the robust check off (``exp_robust``): the link is then applied unchecked, and says so.
    """

    event_id: int
    map_name: str
    link: int
    from_id: int
    to_id: int
    active: bool
    misfit_m: float
    misfit_rad: float
    author: str
    checked: bool
    merged: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        """Return the outcome as the CLI's ``--json`` and the REST answer give it."""
        return {
            "linked": True, "event": self.event_id, "map": self.map_name, "link": self.link, "from": self.from_id,
            "to": self.to_id, "kind": "manual", "active": self.active, "flagged": not self.active,
            "misfit_m": self.misfit_m, "misfit_rad": self.misfit_rad, "author": self.author, "merged": self.merged,
            "checked": self.checked,
            "reason": None if self.active else _reason(self.misfit_m, self.misfit_rad),
        }  # fmt: skip


def _reason(misfit_m: float, misfit_rad: float) -> str:
    return (f"the link contradicts the map: it puts the experience {misfit_m:.3f} m and {misfit_rad:.3f} rad from "
            "where the map's other links hold it; the robust check switched it off (kept, not applied)")  # fmt: skip


# ------------------------------------------------------------------------------------------------ checks


def checked_request(request: LinkRequest) -> LinkRequest:
    """Return the request with its transform as floats and its author trimmed; InputError when it is unusable."""
    values = tuple(float(v) for v in request.transform)
    if len(values) != 4:
        msg = f"a link transform is (dx, dy, dz, dyaw), got {len(values)} values"
        raise InputError(msg)
    for name, value, bound in zip(("dx", "dy", "dz", "dyaw"), values, (MAX_POSITION_M,) * 3 + (MAX_ANGLE_RAD,),
                                  strict=True):  # fmt: skip
        if not math.isfinite(value) or abs(value) > bound:
            msg = f"link transform {name} must be finite and within ±{bound:g}, got {value!r}"
            raise InputError(msg)
    author = request.author.strip()
    if not author or len(author) > MAX_AUTHOR_CHARS or not author.isprintable():
        msg = f"a link's author must be 1-{MAX_AUTHOR_CHARS} printable characters"
        raise InputError(msg)
    if request.to_map == request.map_name:
        request = LinkRequest(request.map_name, request.from_id, request.to_id, None, request.transform, author)
    if request.to_map is None and request.from_id == request.to_id:
        msg = f"cannot link experience {request.from_id} to itself"
        raise InputError(msg)
    return LinkRequest(request.map_name, request.from_id, request.to_id, request.to_map,
                       (values[0], values[1], values[2], values[3]), author)  # fmt: skip


def _check_experience(m: AtlasMap, experience: int) -> None:
    """NotFoundError when map ``m`` has no experience ``experience``."""
    size = int(np.shape(m.snapshot["em_pose"])[0])
    if not 0 <= experience < size:
        msg = f"experience {experience} does not exist in map {m.name!r} (it has {size})"
        raise NotFoundError(msg)


def _check_finished(m: AtlasMap) -> None:
    """MergeError (409) when a session of ``m`` is still being processed: its robot state lives in the map."""
    if m.partial_sessions:
        msg = (f"map {m.name!r} holds a session still being processed (partial); finish it (process its log again) "
               "before linking")  # fmt: skip
        raise MergeError(msg)


def _check_unlinked(state: Mapping[str, np.ndarray], a: int, b: int) -> None:
    """ConflictError when experiences ``a`` and ``b`` are joined by a link already (either way)."""
    src = np.asarray(state["em_link_from"], dtype=np.int64)
    dst = np.asarray(state["em_link_to"], dtype=np.int64)
    if bool(np.any(((src == a) & (dst == b)) | ((src == b) & (dst == a)))):
        msg = f"experiences {a} and {b} are linked already"
        raise ConflictError(msg)


# ------------------------------------------------------------------------------------------------ linking


def _add_and_settle(engine: Engine, a: int, b: int, transform: Sequence[float]) -> tuple[int, bool, float, float]:
    """Add the manual link a → b and settle the map; return (link id, on, misfit metres, misfit radians)."""
    t = np.asarray(transform, dtype=np.float64)
    link = engine.map.link_count
    if not engine.map.add_link_raw(a, b, t, 0.0, float(np.linalg.norm(t[:3])), LinkKind.MANUAL):
        msg = f"experiences {a} and {b} are linked already"
        raise ConflictError(msg)
    engine.settle()
    state = engine.map.snapshot()
    pose = np.asarray(state["em_pose"], dtype=np.float64)
    held = relative(pose[a], pose[b])
    misfit_m = float(np.linalg.norm(held[:3] - t[:3]))
    misfit_rad = abs(float(wrap_angle(held[3] - t[3])))
    return link, bool(np.asarray(state["em_link_active"])[link]), misfit_m, misfit_rad


def _uid(identities: RowIdentities, experience: int) -> list[int]:
    """Return an experience's stable identity [origin session, origin index] (it names the link's ends for good)."""
    sessions, indices = identities.experience_arrays()
    return [int(sessions[experience]), int(indices[experience])]


def _link_details(request: LinkRequest, link: int, ends: tuple[int, int], identities: RowIdentities, active: bool,
                  misfit: tuple[float, float], frames: Mapping[str, int]) -> dict[str, Any]:  # fmt: skip
    """Return the event's ``details``: the link as asked and as added, its author, the sessions' frames."""
    return {
        "link": {"map": request.map_name, "from": request.from_id, "to_map": request.to_map or request.map_name,
                 "to": request.to_id, "transform": list(request.transform), "author": request.author,
                 "id": link, "from_uid": _uid(identities, ends[0]), "to_uid": _uid(identities, ends[1]),
                 "active": active, "misfit_m": misfit[0], "misfit_rad": misfit[1]},
        "session_frames": dict(frames),
        "settle": True,
    }  # fmt: skip


def _session_frames(conn: Connection, session_ids: Sequence[int]) -> dict[str, int]:
    return {str(s.id): s.frames_processed for s in get_sessions(conn=conn, session_ids=list(session_ids))}


def _link_within(db: Database, request: LinkRequest) -> LinkOutcome:
    """Add a manual link inside one map, settle it, and store it with its event and the map's archive."""
    with db.read() as conn:
        m = read_atlas_map(conn, get_map(conn=conn, name=request.map_name).id)
        frames = _session_frames(conn, m.session_ids)
    for experience in (request.from_id, request.to_id):
        _check_experience(m, experience)
    _check_finished(m)
    _check_unlinked(m.snapshot, request.from_id, request.to_id)
    engine = Engine.restore(m.params, m.snapshot)
    link, active, misfit_m, misfit_rad = _add_and_settle(engine, request.from_id, request.to_id, request.transform)
    ends = (request.from_id, request.to_id)
    details = _link_details(request, link, ends, m.identities, active, (misfit_m, misfit_rad), frames)
    rank = int(np.shape(m.snapshot["em_pc"])[1])
    spec = MergeEventSpec(
        map_id=m.id, map_name=m.name, mode=MANUAL_MODE, confirmations=0, lattice_offset=[0.0] * rank,
        transform=IDENTITY_7, yaw=0.0, matches={"link": details["link"]}, target_sessions=m.session_ids,
        source_sessions=[], details={**details, "host": {"name": m.name, "map_id": m.id}},
    )  # fmt: skip
    with db.write() as conn:
        get_map_by_id_or_stale(conn, m.id)
        event_id = record_merge_event(conn=conn, spec=spec)
        archive_map_state(conn=conn, map_id=m.id, event_id=event_id, role="target")
        write_map_state(
            conn=conn, map_id=m.id, expected_version=m.version, params=m.params,
            snapshot={**engine.snapshot(), ID_NEXT_KEY: m.identities.next_table()}, session_ids=m.session_ids,
            template_index=m.identities.template_arrays()[1], experience_index=m.identities.experience_arrays()[1],
        )  # fmt: skip
    return LinkOutcome(event_id, m.name, link, request.from_id, request.to_id, active, misfit_m, misfit_rad,
                       request.author, m.params.exp_robust)  # fmt: skip


def placing_match(a: AtlasMap, b: AtlasMap, from_id: int, to_id: int, transform: Sequence[float]) -> Match:
    """Return the match that places map B so that its experience ``to_id`` lies at A's ``from_id`` ⊕ ``transform``.

    The merge's rigid transform is T = anchor ⊕ partial_pose⁻¹ (Menezes et al. 2023, Eqs. 13-14), with the
    anchor A's experience turned by the link's heading (``relative_rad``, which also turns B's pose-cell
    lattice by that heading): partial_pose = pose_b ⊕ q⁻¹ with q the rest of the link after that turn, so
    T ⊕ pose_b = from ⊕ transform. The partial template is −1: the two views are not identified (a manual
    link joins places whose views differ), and B's lattice is aligned at ``to``'s packet.
    """
    t = np.asarray(transform, dtype=np.float64)
    pose_a = np.asarray(a.snapshot["em_pose"], dtype=np.float64).reshape(-1, 4)[from_id]
    pose_b = np.asarray(b.snapshot["em_pose"], dtype=np.float64).reshape(-1, 4)[to_id]
    anchor = compose(pose_a, np.array([0.0, 0.0, 0.0, t[3]]))
    q = relative(anchor, compose(pose_a, t))
    partial_pose = compose(pose_b, inverse(q))
    packet = np.asarray(b.snapshot["em_pc"], dtype=np.float64)[to_id]
    return Match(
        stored_template=int(np.asarray(a.snapshot["em_template"])[from_id]), stored_experience=from_id,
        partial_template=-1, partial_pose=tuple(float(v) for v in partial_pose),
        partial_packet=tuple(float(v) for v in packet), relative_rad=float(t[3]), confirmations=0,
    )  # fmt: skip


def _link_across(db: Database, request: LinkRequest) -> LinkOutcome:
    """Merge map B into map A through a manual link; store the merged map with its event and both archives."""
    assert request.to_map is not None
    with db.read() as conn:
        a = read_atlas_map(conn, get_map(conn=conn, name=request.map_name).id)
        b = read_atlas_map(conn, get_map(conn=conn, name=request.to_map).id)
        sessions = sorted(set(a.session_ids) | set(b.session_ids))
        frames = _session_frames(conn, sessions)
    _check_experience(a, request.from_id)
    _check_experience(b, request.to_id)
    for m in (a, b):
        _check_finished(m)
    match = placing_match(a, b, request.from_id, request.to_id, request.transform)
    partial = {**b.snapshot, "em_current": np.asarray(-1, dtype=np.int64)}  # no Eq. 17 link: the manual one joins
    engine, record = merge_snapshots(a.stored(), StoredMap(b.id, b.params, partial), match, settle=False)
    to_id = int(record.experience_map[request.to_id])
    link, active, misfit_m, misfit_rad = _add_and_settle(engine, request.from_id, to_id, request.transform)
    identities = RowIdentities.merged(a.identities, b.identities, record)
    host = a if a.id < b.id else b
    details = _link_details(request, link, (request.from_id, to_id), identities, active, (misfit_m, misfit_rad), frames)
    merge = MergeToWrite(
        mode=MANUAL_MODE, target=a, partial=PartialSide(b.name, b.id, None, b.identities, b.params, b.session_ids,
                                                        from_store=True),
        match=match, record=record, host_id=host.id, host_name=host.name,
        details={**details, "match": match_to_dict(match), "record": record_summary(record),
                 "source": {"name": b.name, "map_id": b.id}, "target": {"name": a.name, "map_id": a.id}},
    )  # fmt: skip
    with db.write() as conn:
        written = write_merges(
            conn, merges=[merge], claimed={a.id: a.version, b.id: b.version}, host_id=host.id, params=a.params,
            snapshot=engine.snapshot(), identities=identities, tags={}, session_ids=sessions,
        )  # fmt: skip
    merged = [n for n in (a.name, b.name) if n != written.host_name]
    return LinkOutcome(written.event_ids[0], written.host_name, link, request.from_id, to_id, active, misfit_m,
                       misfit_rad, request.author, a.params.exp_robust, merged=merged)  # fmt: skip


def link_experiences(db: Database, request: LinkRequest) -> LinkOutcome:
    """Add a manual link (within one map, or across two, which then merge); return what it did.

    Raises:
        InputError: a transform value not finite or beyond its bound, no author, an experience linked to itself.
        NotFoundError: an unknown map or experience.
        ConflictError: the two experiences are linked already; a map holds a session still being processed
            (``MergeError``); the maps cannot be merged (parameters); a map changed meanwhile (``StaleMapError``).
    """
    request = checked_request(request)
    if request.to_map is None:
        return _link_within(db, request)
    return _link_across(db, request)


__all__ = ["MANUAL_MODE", "LinkOutcome", "LinkRequest", "checked_request", "link_experiences", "placing_match"]

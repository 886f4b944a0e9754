"""A session being mapped with online merging: the per-frame bookkeeping between engine, merger and store.

:func:`mapserver.processing.pipeline.process_into_store` feeds every frame to :meth:`LiveSession.on_step`.
It keeps what the store will need when the session is written: the map the session is in at the
moment (its own, or the stored map it merged into), the stable row identities of that map, the
merges made (:class:`PendingMerge`, each ``applied`` or ``rejected``), the frames' stamps and the
evidence images. The dead reckoning is the run's: :func:`mapserver.processing.run.run_engine` integrates each
frame's motion into it before the frame is booked here, and a merge records the pose it has reached.
A merge swaps the engine for the merged one; a merge rolled back by its verification swaps it back
for the session's own engine, restores the map it was in before and keeps the merge as ``rejected``
with its evidence.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from core import Action, Engine, Params, StepResult
from mapserver.merge import MergeEvent, OnlineMerger, Rollback
from mapserver.merge.identity import RowIdentities
from mapserver.merge.provenance import match_to_dict, record_summary
from mapserver.merge.relevance import ViewLog
from mapserver.merge.verify import SessionFrame
from mapserver.statuses import MergeStatus

if TYPE_CHECKING:
    from mapserver.atlas import AtlasMap
    from mapserver.processing.reckoning import DeadReckoning

logger = logging.getLogger(__name__)


@dataclass(eq=False)
class Holder:
    """The map a session is in at the moment: stored id and name (None: not stored yet), its other sessions."""

    id: int | None
    name: str
    sessions: list[int]
    engine: Engine
    ids: RowIdentities


@dataclass(eq=False)
class PendingMerge:
    """An online merge made during the run, stored in the session's write transaction.

    ``status`` is ``applied``, or ``rejected`` when its verification rolled it back (the maps are then
    as if it never happened; only the event with its evidence is stored).
    """

    event: MergeEvent
    target: AtlasMap
    before: Holder  # the map the session was in before the merge (partial side; restored by a rollback)
    frames_at: int
    reckoning_pose: list[float]
    host_id: int
    host_name: str
    status: MergeStatus = MergeStatus.APPLIED
    rejected_at: int | None = None
    activations_before: list[tuple[float, int, int, float]] = field(default_factory=list, repr=False)
    """The activation timeline as booked when the merge was made (a rollback restores it)."""

    @property
    def partial_ids(self) -> RowIdentities:
        """Return the partial map's row identities right before the merge."""
        return self.before.ids

    @property
    def partial_name(self) -> str:
        """Return the partial map's name."""
        return self.before.name

    @property
    def partial_map_id(self) -> int | None:
        """Return the partial map's stored id (None: the session's new map)."""
        return self.before.id

    @property
    def partial_sessions(self) -> list[int]:
        """Return the stored sessions in the partial map besides the running one."""
        return self.before.sessions


@dataclass(eq=False)
class LiveSession:
    """The running session's bookkeeping (see the module docstring)."""

    holder: Holder
    tag: int
    start: int
    merger: OnlineMerger | None
    targets: dict[int, AtlasMap]  # stored map id → the merge candidates
    collector: Any  # mapserver.store.evidence.EvidenceCollector
    reckoning: DeadReckoning  # the run's, read here (run_engine integrates each frame)
    stamps: list[float] = field(default_factory=list)
    pending: list[PendingMerge] = field(default_factory=list)
    activations: list[tuple[float, int, int, float]] = field(default_factory=list)
    """Per frame: stamp, the active template's identity (origin tag, origin index; −1, −1 for none), created."""
    views: ViewLog | None = None
    """Every frame's view, when merging (the stale check's relevance test, :mod:`mapserver.merge.relevance`)."""

    @property
    def applied(self) -> list[PendingMerge]:
        """Return the merges that stand."""
        return [m for m in self.pending if m.status == MergeStatus.APPLIED]

    def on_step(self, frame: SessionFrame, result: StepResult) -> Engine | None:
        """Book one frame; return the engine to continue in when a merge or a rollback changed it."""
        holder = self.holder
        holder.ids.extend(holder.engine.template_count, holder.engine.experience_count, self.tag)
        stamp = frame.stamp_ns * 1e-9
        self.stamps.append(stamp)
        self._activate(holder.ids, stamp, result.template, result.template_created)
        self.collector.observe(stamp, frame.image)
        if result.action == Action.CREATE_NODE:
            self.collector.experience(holder.ids.experience_identity(result.experience)[1], stamp)
        if self.views is not None:
            self.views.add(holder.engine.local_view.last_view)
        if self.merger is None:
            return None
        event = self.merger.observe(holder.engine, result, frame)
        if isinstance(event, MergeEvent):
            return self._merged(event)
        if isinstance(event, Rollback):
            return self._rolled_back(event)
        return None

    def finish(self) -> Engine | None:
        """End the log: judge a probation still running; return the engine to store when it rolled its merge back."""
        rollback = None if self.merger is None else self.merger.finish()
        return None if rollback is None else self._rolled_back(rollback)

    def _activate(self, ids: RowIdentities, stamp: float, template: int, created: bool) -> None:
        """Book the frame's active template by its stable identity (renumbering by merges cannot change it)."""
        tag, index = ids.template_identity(template)
        self.activations.append((stamp, tag, index, float(created)))

    def activation_rows(self, tags: dict[int, int]) -> np.ndarray:
        """Return the activations (N, 4) with origin tags replaced by ``tags`` (the new session's id)."""
        rows = np.asarray(self.activations, dtype=np.float64).reshape(-1, 4)
        for old, new in tags.items():
            rows[rows[:, 1] == old, 1] = new
        return rows

    def _merged(self, event: MergeEvent) -> Engine:
        """Continue in the merged engine, in the map that hosts the merge (the oldest of the two)."""
        holder, target = self.holder, self.targets[int(event.key)]  # type: ignore[call-overload]
        before = Holder(holder.id, holder.name, list(holder.sessions), holder.engine, holder.ids.copy())
        if holder.id is None or target.id < holder.id:
            host_id, host_name = target.id, target.name
        else:
            host_id, host_name = holder.id, holder.name
        self.pending.append(
            PendingMerge(
                event=event, target=target, before=before, frames_at=self.start + len(self.stamps),
                reckoning_pose=[float(v) for v in self.reckoning.pose], host_id=host_id, host_name=host_name,
                activations_before=list(self.activations),
            )
        )  # fmt: skip
        self.holder = Holder(
            id=host_id, name=host_name, sessions=sorted(set(holder.sessions) | set(target.session_ids)),
            engine=event.engine, ids=RowIdentities.merged(target.identities, holder.ids, event.record),
        )  # fmt: skip
        self._reidentify(before.ids, self.holder.ids, np.asarray(event.record.template_map, dtype=np.int64))
        return event.engine

    def _reidentify(self, before: RowIdentities, after: RowIdentities, template_map: np.ndarray) -> None:
        """Rename the booked frames' templates through a merge: an identified template takes the stored one's name."""
        tags, index = before.template_arrays()
        row_of = {(int(t), int(i)): k for k, (t, i) in enumerate(zip(tags.tolist(), index.tolist(), strict=True))}
        new_tags, new_index = after.template_arrays()
        for n, (stamp, tag, idx, created) in enumerate(self.activations):
            k = row_of.get((tag, idx))
            if k is not None and k < template_map.size:
                m = int(template_map[k])
                self.activations[n] = (stamp, int(new_tags[m]), int(new_index[m]), created)

    def _rolled_back(self, rollback: Rollback) -> Engine:
        """Go back to the map the session was in before the merge, in the engine that never merged."""
        merge = next(m for m in self.pending if m.event is rollback.event)
        merge.status, merge.rejected_at = MergeStatus.REJECTED, self.start + len(self.stamps)
        before = merge.before
        ids = before.ids.copy()
        first_new = ids.experiences
        ids.extend(rollback.engine.template_count, rollback.engine.experience_count, self.tag)
        index = ids.experience_arrays()[1]
        self.collector.replace_from(
            int(index[first_new]) if first_new < len(index) else 1 << 62,
            [(int(index[e]), stamp, image) for e, stamp, image in rollback.created],
        )
        self.holder = Holder(before.id, before.name, list(before.sessions), rollback.engine, ids)
        self.activations = list(merge.activations_before)  # then the probation's frames as its engine saw them
        for stamp, template, created in rollback.seen:
            self._activate(ids, stamp, template, created)
        return rollback.engine


def merge_to_write(m: Any, pending: list[Any], session_id: int, params: Params, frames_now: Mapping[int, int]) -> Any:
    """Return the store's view of one online merge (:class:`PendingMerge`) with its provenance."""
    from mapserver import atlas

    ev = m.event
    partial = atlas.PartialSide(
        name=m.partial_name, map_id=m.partial_map_id, snapshot=ev.partial, identities=m.partial_ids,
        params=params, session_ids=sorted({session_id, *m.partial_sessions}),
    )  # fmt: skip
    details = {
        "frame": int(ev.frame), "stamp": float(ev.stamp), "session": session_id, "frames_at": m.frames_at,
        "reckoning_pose": m.reckoning_pose, "odometry": [float(v) for v in ev.odometry],
        **({} if ev.session_pose is None else {"session_pose": [float(v) for v in ev.session_pose]}),
        "match": match_to_dict(ev.match), "record": record_summary(ev.record),
        "target": {"name": m.target.name, "map_id": m.target.id},
        "source": {"name": m.partial_name, "map_id": m.partial_map_id},
        "absorbed": [e.target.name for e in pending[: pending.index(m)] if e.status == MergeStatus.APPLIED],
        "session_frames": {str(k): int(v) for k, v in frames_now.items()},
        "evidence": ev.evidence, "status": m.status,
    }  # fmt: skip
    if m.rejected_at is not None:
        details["rejected_at_frame"] = m.rejected_at
    return atlas.MergeToWrite(
        mode="online", target=m.target, partial=partial, match=ev.match, record=ev.record,
        host_id=m.host_id, host_name=m.host_name, details=details,
    )  # fmt: skip

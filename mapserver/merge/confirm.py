"""Confirmation of a merge: K consecutive matching frames that agree on one alignment.

The paper merges on the first frame whose view matches a stored template (K = 1), so two
places that look alike are merged by mistake. Here a merge needs K consecutive frames whose
views match templates of the same stored map (same matcher and threshold as the engine)
**and** whose matches agree with the session's odometry:

* every matching frame t gives an alignment ``A_t = (p_u ⊕ rel) ⊕ O_t⁻¹`` between the
  session's odometry frame (pose O_t, integrated from the engine's motion) and the stored
  map (p_u: the stored experience of the matched template, rel: the view's heading offset);
* frame t extends the streak when, for every frame s already in it, ``A_s ⊕ O_t`` (where the
  stored map should be seen at t if s was right) lies within ``position_tolerance`` metres
  and ``yaw_tolerance`` radians of ``p_u ⊕ rel``; otherwise the streak restarts from the
  frames that do agree with t;
* with K ≥ 2 the matched stored templates must also advance: at least two distinct stored
  templates in the streak (a robot standing still, or one look-alike view seen for several
  frames, is one piece of evidence, not K);
* a frame whose view matches no template of that map ends the streak; a frame matching a
  stored template that has no experience (the stored session's gates skipped it) carries no
  geometry: it neither extends nor ends the streak.

So the matched stored experiences must advance along the stored map as the robot's odometry
advances: a look-alike place elsewhere gives alignments that disagree (different position
or heading), or is too short a look-alike to give K frames and two templates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.angles import wrap_angle
from core.arrays import FloatArray
from core.se3 import alignment, compose


@dataclass(frozen=True, eq=False)
class Observation:
    """One frame's match of the current view against one stored map.

    Attributes:
        frame: frame index in the session.
        stored_template: matched stored template u.
        stored_experience: the stored experience chosen for u (−1: u has none).
        error: the matcher's error (≤ the threshold).
        relative_rad: the view's heading offset relative to u.
        partial_template: the session engine's current template for the same view.
        odometry: (4,) the session's odometry pose at the frame (x, y, z, yaw).
        packet: (D,) the session's pose-cell packet centre at the frame.
        seen: (4,) where the stored map says the robot is: ``p_u ⊕ (0, 0, 0, rel)``.
    """

    frame: int
    stored_template: int
    stored_experience: int
    error: float
    relative_rad: float
    partial_template: int
    odometry: FloatArray
    packet: FloatArray
    seen: FloatArray

    @property
    def has_geometry(self) -> bool:
        """Return whether the matched template has a stored experience (a pose to align with)."""
        return self.stored_experience >= 0

    @property
    def alignment(self) -> FloatArray:
        """Return A = seen ⊕ odometry⁻¹ (4,): odometry frame → stored map frame."""
        return alignment(self.seen, self.odometry)


class Streak:
    """The running confirmation for one stored map (see the module docstring for the rule).

    Args:
        needed: K, the consecutive consistent frames needed (≥ 1).
        position_tolerance: metres between the predicted and matched stored positions.
        yaw_tolerance: radians between the predicted and matched headings.
    """

    def __init__(self, needed: int, position_tolerance: float, yaw_tolerance: float) -> None:
        if needed < 1:
            msg = f"confirmation needs at least one frame, got {needed!r}"
            raise ValueError(msg)
        self.needed = needed
        self.position_tolerance = position_tolerance
        self.yaw_tolerance = yaw_tolerance
        self.entries: list[Observation] = []
        self.neutral: list[Observation] = []

    def reset(self) -> None:
        """Forget the streak (a frame without match, or the engine changed under it)."""
        self.entries.clear()
        self.neutral.clear()

    def agrees(self, earlier: Observation, later: Observation) -> bool:
        """Return whether ``later``'s match is where ``earlier``'s alignment predicts it."""
        predicted = compose(earlier.alignment, later.odometry)
        gap = float(np.linalg.norm(predicted[:3] - later.seen[:3]))
        turn = abs(float(wrap_angle(predicted[3] - later.seen[3])))
        return gap <= self.position_tolerance and turn <= self.yaw_tolerance

    def predict(self, odometry: FloatArray) -> FloatArray | None:
        """Return where the latest entry's alignment puts the robot in the stored map (None: no entry)."""
        if not self.entries:
            return None
        return compose(self.entries[-1].alignment, odometry)

    def add(self, observation: Observation) -> bool:
        """Add a matching frame; return True when the streak confirms a merge."""
        if not observation.has_geometry:
            if self.entries:
                self.neutral.append(observation)
            return False
        keep = len(self.entries)
        while keep > 0 and self.agrees(self.entries[keep - 1], observation):
            keep -= 1
        if keep:
            first_kept = self.entries[keep].frame if keep < len(self.entries) else observation.frame
            self.entries = self.entries[keep:]
            self.neutral = [n for n in self.neutral if n.frame > first_kept]
        self.entries.append(observation)
        return self.confirmed

    @property
    def confirmed(self) -> bool:
        """Return whether the streak holds K agreeing frames (and two stored templates when K ≥ 2)."""
        if len(self.entries) < self.needed:
            return False
        if self.needed == 1:
            return True
        return len({e.stored_template for e in self.entries}) >= 2

    @property
    def best(self) -> Observation:
        """Return the streak's best-matching frame (lowest error; the latest on ties): the merge anchor."""
        return min(reversed(self.entries), key=lambda e: e.error)

    def pairs(self) -> tuple[tuple[int, int], ...]:
        """Return the (session template, stored template) pairs seen in the streak, in frame order."""
        seen = sorted([*self.entries, *self.neutral], key=lambda e: e.frame)
        return tuple((e.partial_template, e.stored_template) for e in seen)

"""PoseidonSLAM's back-end event gates: VPR Guard (thesis Eqs. 4.11–4.14) and the motion gate."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from core.config import Params


class EventGate:
    """Decides whether a proposed new experience (an ``/experience_event``) may be created.

    VPR Guard keeps the last ``vpr_window`` emitted view ids. For the current id
    ℓ_t, C_t = #{i < w : ℓ_{t−i} = ℓ_t} (Eq. 4.11, window includes the current
    emission); g_t = [C_t ≥ vpr_min_rep] (Eq. 4.12); the rejection counter q_t
    grows while g_t = 0 and resets when it is 1 (Eq. 4.13); the leak accepts when
    q_t ≥ vpr_leak_rate and then resets q (Eq. 4.14). The guard is evaluated on
    every emission; an event needs the guard (when enabled) **and** the motion
    gate (when enabled): horizontal displacement ≥ ``min_event_trans_xy`` or
    vertical ≥ ``min_event_dz`` since the last experience (the thesis leaves
    AND/OR open; OR is used, see notes/poseidonslam.md §4.4).
    """

    def __init__(self, params: Params) -> None:
        self.params = params
        self.history = np.full(params.vpr_window, -1, dtype=np.int64)
        self.rejections = 0
        self._accepted = True

    def observe(self, template: int) -> bool:
        """Record an emitted view id and return the guard's decision g̃_t for it."""
        p = self.params
        if not p.vpr_guard:
            self._accepted = True
            return True
        self.history[:-1] = self.history[1:]
        self.history[-1] = template
        count = int(np.count_nonzero(self.history == template))
        accepted = count >= p.vpr_min_rep
        if accepted:
            self.rejections = 0
        else:
            self.rejections += 1
            if self.rejections >= p.vpr_leak_rate:
                accepted = True
                self.rejections = 0
        self._accepted = accepted
        return accepted

    def allows_event(self, accum_dx: float, accum_dy: float, accum_dz: float) -> bool:
        """Return whether a new experience may be created now (guard result and motion gate)."""
        p = self.params
        if not self._accepted:
            return False
        if not p.motion_gate:
            return True
        return math.hypot(accum_dx, accum_dy) >= p.min_event_trans_xy or abs(accum_dz) >= p.min_event_dz

    def snapshot(self) -> dict[str, np.ndarray]:
        """Return the gate state (keys ``gate_*``)."""
        return {
            "gate_history": self.history.copy(),
            "gate_state": np.array([float(self.rejections), 1.0 if self._accepted else 0.0, 0.0]),
        }

    @classmethod
    def restore(cls, params: Params, state: Mapping[str, np.ndarray]) -> EventGate:
        """Rebuild the gate from :meth:`snapshot` arrays."""
        gate = cls(params)
        history = np.asarray(state["gate_history"], dtype=np.int64)
        if history.shape == gate.history.shape:
            gate.history = history.copy()
        values = np.asarray(state["gate_state"], dtype=np.float64)
        gate.rejections = int(values[0])
        gate._accepted = bool(values[1] > 0.5)
        return gate

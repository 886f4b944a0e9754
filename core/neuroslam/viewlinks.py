"""NeuroSLAM's local-view calibration: which template injects, how much, and where (notes ``neuroslam.md`` §1.5).

The paper writes the view → pose-cell association as a Hebbian matrix Ψ (Eqs. 10–11); the authors' code, which
produced the figures, keeps one cell per template instead, and so does this module:

* a new template stores the codes decoded at the end of the previous frame (grid x, y, z; head yaw, height);
* every frame every template's novelty ``decay`` falls by ``global_decay`` (floored at 0); the template seen
  this frame gains ``active_decay``;
* a template injects only once it has been re-entered from another template (its "first" flag clears when it
  is matched while the previous frame's template was a different one): a template never injects on the frames
  that made it;
* it injects ``δ (30 − e^{1.2·decay}) / 30`` into each network at its stored codes (``δ`` per network,
  Tables 5–6), so a view seen again within a few frames stops injecting (decay above ln 30 / 1.2 ≈ 2.83).

Defaults: SynPerData's code values ``VT_ACTIVE_DECAY`` 2.0 and ``VT_GLOBAL_DECAY`` 0.1 (notes §4, Table 7).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from core.neuroslam.attractor import FloatArray
from core.neuroslam.networks import Codes, ConjunctivePoseCells


@dataclass(frozen=True)
class ViewDecay:
    """How fast a template's novelty wears off when seen, and recovers every frame (notes §1.5)."""

    active_decay: float = 2.0
    global_decay: float = 0.1


class ViewLinks:
    """Per template: the codes it was made at, its novelty decay and whether it has been re-entered."""

    def __init__(self, decay: ViewDecay | None = None) -> None:
        self.decay_params = decay or ViewDecay()
        self.codes: list[FloatArray] = []
        self.decay: FloatArray = np.zeros(0, dtype=np.float64)
        self.first: list[bool] = []
        self.previous = -1

    @property
    def count(self) -> int:
        """Templates known."""
        return len(self.codes)

    def on_view(self, template: int, created: bool, cells: ConjunctivePoseCells) -> bool:
        """Record this frame's template and inject its energy into ``cells``; whether it injected.

        Raises:
            ValueError: a created template whose id is not the next one, or a known id never created.
        """
        np.maximum(self.decay - self.decay_params.global_decay, 0.0, out=self.decay)
        injected = False
        if created:
            if template != self.count:
                msg = f"template {template} created, but {self.count} is the next id"
                raise ValueError(msg)
            self.codes.append(cells.codes.as_array())
            self.decay = np.append(self.decay, self.decay_params.active_decay)
            self.first.append(True)
        elif not 0 <= template < self.count:
            msg = f"template {template} was never created ({self.count} known)"
            raise ValueError(msg)
        else:
            self.decay[template] += self.decay_params.active_decay
            if self.first[template] and template != self.previous:
                self.first[template] = False
            if not self.first[template]:
                code = self.codes[template]
                stored = Codes(grid=(float(code[0]), float(code[1]), float(code[2])),
                               head=(float(code[3]), float(code[4])))
                injected = cells.calibrate(stored, float(self.decay[template]))
        self.previous = template
        return injected

    def snapshot(self) -> dict[str, FloatArray]:
        """The links as arrays: codes (T, 5), decay (T,), first (T,) as 0/1, and the previous template."""
        return {
            "nl_codes": np.asarray(self.codes, dtype=np.float64).reshape(-1, 5),
            "nl_decay": self.decay.copy(),
            "nl_first": np.asarray(self.first, dtype=np.float64),
            "nl_previous": np.asarray([self.previous], dtype=np.float64),
        }

    @classmethod
    def restore(cls, state: Mapping[str, FloatArray], decay: ViewDecay | None = None) -> ViewLinks:
        """The links as :meth:`snapshot` saved them."""
        links = cls(decay)
        links.codes = [row.copy() for row in np.asarray(state["nl_codes"], dtype=np.float64).reshape(-1, 5)]
        links.decay = np.array(state["nl_decay"], dtype=np.float64)
        links.first = [bool(f) for f in np.asarray(state["nl_first"]).tolist()]
        links.previous = int(np.asarray(state["nl_previous"])[0])
        if not len(links.codes) == len(links.decay) == len(links.first):
            raise ValueError("the saved view links' arrays differ in length")
        return links

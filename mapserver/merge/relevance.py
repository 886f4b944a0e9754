"""Which changes to the atlas a finished session must be processed again for (the stale check's relevance test).

A session is matched, frame by frame, against the merge candidates read when it started. A stored map
that changes or appears while it runs is a map the session never saw as it is now; the rule so far was to
process the log again whenever that happens (``mapserver.atlas.ensure_candidates_unchanged``), so with W
sessions in flight every commit sent the W − 1 others back to their first frame, even when their maps had
nothing to do with each other (docs/scaling.md: 2 workers gave 1.0× one with merging on).

The merge decision (:mod:`mapserver.merge.hypotheses`) sees a stored map only through the session's frames
whose view matches one of its templates (*observations*) and, once a map has them, through that map's
places. So a changed or new map cannot change any decision of the session when

* the session made no observation of it (nor merged into it), and
* none of the session's frames' views matches any of its templates as they are now.

Then the session's run is exactly what it would have been against the atlas as it is now, and it is stored
without a rerun. Anything else (an observed map changed, a view matches, or the session's views are not
all known: a resumed session, a front-end whose views are not intensity templates) keeps the rerun.

The session keeps every frame's view (:class:`ViewLog`) in 8 bits per value. The test widens the match
threshold by half a quantisation step and switches the template-mean prefilter off, so a view that would
match in the engine's arithmetic is never missed; a false alarm only costs the rerun that was the rule.
"""

from __future__ import annotations

import numpy as np

from core import Params
from core.arrays import Float32Array
from core.localview import LocalViewCells

QUANTUM = 1.0 / 255.0
"""One step of the stored views (values in [0, 1] as 8 bits)."""
MAX_BYTES = 256 * 2**20
"""Views beyond this many bytes are not kept (the log gives up: every change then means a rerun)."""


class ViewLog:
    """Every frame's view of a running session, 8 bits per value (``complete`` False once one is missing)."""

    def __init__(self, complete: bool = True, max_bytes: int = MAX_BYTES) -> None:
        self.complete = complete
        self.max_bytes = max_bytes
        self._views: list[np.ndarray] = []
        self._bytes = 0

    def __len__(self) -> int:
        return len(self._views)

    def add(self, view: np.ndarray | None) -> None:
        """Keep one frame's view (an intensity template with values in [0, 1]; anything else: give up)."""
        if not self.complete:
            return
        values = None if view is None else np.asarray(view)
        if values is None or values.dtype.kind != "f" or values.size == 0 or not (
            float(values.min()) >= 0.0 and float(values.max()) <= 1.0
        ):
            self.give_up()
            return
        self._views.append(np.rint(values * 255.0).astype(np.uint8))
        self._bytes += values.size
        if self._bytes > self.max_bytes:
            self.give_up()

    def give_up(self) -> None:
        """Forget the views: the session's views are no longer all known."""
        self.complete = False
        self._views.clear()
        self._bytes = 0

    def any_match(self, templates: Float32Array, params: Params) -> bool:
        """Return whether some kept view may match one of ``templates`` (True when the views are not all known).

        ``params``: the session's (template geometry, shift, threshold). The threshold is widened by half a
        quantisation step (a stored view is off by at most that much per value) and the mean prefilter is
        off, so every view that matched in the engine's arithmetic matches here.
        """
        if not self.complete:
            return True
        stored = np.asarray(templates, dtype=np.float32)
        if stored.size == 0 or not self._views:
            return False
        stored = stored.reshape(-1, params.template_y_size, params.template_x_size)
        cells = LocalViewCells(params.replace(vt_mean_prefilter_epsilon=2.0))  # every mean passes
        cells.add_templates(stored, stored.reshape(stored.shape[0], -1).mean(axis=1, dtype=np.float64))
        limit = params.vt_match_threshold + 0.5 * QUANTUM + 1e-6
        for view in self._views:
            values = view.astype(np.float32) / np.float32(255.0)
            if cells.match(values, float(values.mean(dtype=np.float64)), limit=limit)[0] >= 0:
                return True
        return False

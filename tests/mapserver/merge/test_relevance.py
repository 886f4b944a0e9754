"""The stale check's relevance test (mapserver.merge.relevance): which views may meet a changed map."""

from __future__ import annotations

import numpy as np
import pytest

from core import Params
from mapserver.merge.relevance import ViewLog

PARAMS = Params().replace(template_x_size=12, template_y_size=3, vt_shift_match=2, vt_step_match=1,
                          vt_match_threshold=0.05, vt_patch_normalise=0)  # fmt: skip


def _template(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.1, 0.9, (3, 12)).astype(np.float32)


def test_a_view_of_the_same_place_meets_the_map_and_one_of_another_does_not() -> None:
    stored = np.stack([_template(1), _template(2)])
    same, other = ViewLog(), ViewLog()
    same.add(np.roll(_template(2), 1, axis=1))  # the place seen one column further on
    other.add(_template(3))
    assert same.any_match(stored, PARAMS)
    assert not other.any_match(stored, PARAMS)


@pytest.mark.parametrize("error", [0.049, 0.05])
def test_a_view_just_within_the_threshold_is_never_missed_after_8_bit_storage(error: float) -> None:
    """Every compared value off by exactly ``error``: the engine matches it (≤ 0.05), so must the test."""
    template = np.round(_template(4) * 255) / 255  # exact 8-bit values: the error is all the view's offset
    view = template.copy()
    view[:, 2:10] += error
    log = ViewLog()
    log.add(view)
    assert log.any_match(template[None].astype(np.float32), PARAMS)


def test_views_that_are_not_all_known_meet_everything() -> None:
    stored = np.stack([_template(1)])
    resumed = ViewLog(complete=False)  # a resumed session: its first frames ran in another process
    resumed.add(_template(3))
    assert resumed.any_match(stored, PARAMS)
    descriptor = ViewLog()  # an sdr-htm front-end's view is a set of cell ids, not an intensity template
    descriptor.add(np.array([3, 17, 40], dtype=np.int64))
    assert not descriptor.complete and descriptor.any_match(stored, PARAMS)
    capped = ViewLog(max_bytes=50)  # one 36-value view fits, the second passes the cap
    capped.add(_template(3))
    assert capped.complete
    capped.add(_template(5))
    assert not capped.complete and len(capped) == 0 and capped.any_match(stored, PARAMS)
    assert not ViewLog().any_match(stored, PARAMS)  # no frame at all: nothing can meet the map

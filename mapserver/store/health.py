"""A stored map's health figure (issue 12): how well its active links agree, and how many are switched off."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from core.config import Params
from core.robust import Drift, health


def map_health(params: Any, snapshot: Mapping[str, Any]) -> dict[str, float | int]:
    """Return a map state's health ``{"residual", "worst", "switched_off", "links", "unmeasured"}``.

    Computed by :func:`core.robust.health`: ``residual`` is the RMS over the active links of each link's
    residual divided by the
    odometry drift expected over one link length (``exp_robust_drift`` m/m and
    ``exp_robust_yaw_drift`` rad/m times the median odometry link length): 0.5–1.2 on the
    simulator's consistent maps; ``worst`` (the largest) is above ``exp_robust_threshold``
    (4 by default) when an active link contradicts the rest. ``params`` is a ``core.Params`` or its dict
    (missing keys take the defaults).
    """
    if not isinstance(params, Params):  # a stored map's parameter dict: the keys this engine knows
        params = Params().replace(**{k: v for k, v in dict(params or {}).items() if k in Params.__dataclass_fields__})
    drift = Drift.of(params)
    src = np.asarray(snapshot["em_link_from"], dtype=np.int64).reshape(-1)
    active = np.ones(src.size, dtype=bool)
    given = np.asarray(snapshot.get("em_link_active", np.zeros(0, dtype=bool)), dtype=bool).reshape(-1)
    active[: min(given.size, src.size)] = given[: src.size]
    return health(
        np.asarray(snapshot["em_pose"], dtype=np.float64).reshape(-1, 4),
        src,
        np.asarray(snapshot["em_link_to"], dtype=np.int64).reshape(-1),
        np.asarray(snapshot["em_link_transform"], dtype=np.float64).reshape(-1, 4),
        np.asarray(snapshot["em_link_kind"]).reshape(-1),
        np.asarray(snapshot["em_link_distance"], dtype=np.float64).reshape(-1),
        active,
        drift,
    )

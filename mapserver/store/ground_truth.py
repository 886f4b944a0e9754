"""A session's ground truth: the log's reference poses, decimated in time, kept beside the session.

``process`` keeps the ground-truth topic of a log that has one; ``mapserver ground-truth`` and
``PUT /v1/sessions/{name}/ground-truth`` give it (a TUM file) to a session stored without it. Rows are
``[stamp, x, y, z, qx, qy, qz, qw]`` (seconds, metres, unit quaternion), float64 little-endian, N × 8, in
stamp order. :func:`decimate_ground_truth` keeps the first sample of every :data:`GROUND_TRUTH_SPACING_S`
(0.1 s) of log time and the last sample, at most :data:`MAX_GROUND_TRUTH_ROWS` rows (the spacing widens
for longer logs): the linear interpolation the APE takes between kept samples differs from the full rate's
by the chord of 0.1 s of driving (under a millimetre at walking and driving speeds on the simulator's
routes; measured in the tests).
"""

from __future__ import annotations

from collections.abc import Collection

import numpy as np
import numpy.typing as npt
from sqlalchemy import Connection, select, update

from mapserver.errors import InputError, NotFoundError
from mapserver.store.models import Session

GROUND_TRUTH_COLUMNS = 8
"""``[stamp, x, y, z, qx, qy, qz, qw]``."""

GROUND_TRUTH_SPACING_S = 0.1
"""Log time (s) between kept ground-truth samples (the first sample of each such interval is kept)."""

BIN_SLACK = 1e-6
"""Fraction of the spacing by which a sample stamped just before an interval's start still counts in it: at
exactly 1 / spacing Hz, rounding in ``stamp − first stamp`` would otherwise drop samples at random."""

MAX_GROUND_TRUTH_ROWS = 100_000
"""Most rows kept per session (6.4 MB): a log longer than 2.8 hours keeps samples further apart."""


def decimate_ground_truth(
    rows: npt.ArrayLike, *, spacing_s: float = GROUND_TRUTH_SPACING_S, max_rows: int = MAX_GROUND_TRUTH_ROWS
) -> npt.NDArray[np.float64]:
    """Return the rows in stamp order, one per ``spacing_s`` of log time (the first of each interval) and the last.

    The spacing widens to ``span / (max_rows - 2)`` when that is larger, so at most ``max_rows`` rows remain.

    Raises:
        InputError: the rows are not N × 8 finite numbers, or there are none.
    """
    array = np.asarray(rows, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != GROUND_TRUTH_COLUMNS or array.shape[0] == 0:
        msg = f"ground truth must be rows of [stamp, x, y, z, qx, qy, qz, qw], got shape {array.shape}"
        raise InputError(msg)
    if not np.isfinite(array).all():
        msg = "ground truth holds a number that is not finite"
        raise InputError(msg)
    array = array[np.argsort(array[:, 0], kind="stable")]
    stamps = array[:, 0]
    span = float(stamps[-1] - stamps[0])
    step = max(spacing_s, span / max(max_rows - 2, 1))
    if step <= 0.0:
        return np.ascontiguousarray(array[:max_rows])
    bins = np.floor((stamps - stamps[0]) / step + BIN_SLACK).astype(np.int64)
    keep = np.zeros(stamps.size, dtype=bool)
    keep[np.flatnonzero(np.diff(bins, prepend=-1))] = True  # the first sample of each interval
    keep[-1] = True
    return np.ascontiguousarray(array[keep])


def _blob(rows: npt.NDArray[np.float64]) -> bytes:
    return np.ascontiguousarray(rows, dtype="<f8").reshape(-1, GROUND_TRUTH_COLUMNS).tobytes()


def _rows(blob: bytes) -> npt.NDArray[np.float64]:
    return np.frombuffer(blob, dtype="<f8").reshape(-1, GROUND_TRUTH_COLUMNS).astype(np.float64)


def set_ground_truth(*, conn: Connection, session_id: int, rows: npt.ArrayLike) -> int:
    """Store a session's ground truth (decimated, replacing what was stored); return the rows kept.

    Raises:
        InputError: rows that :func:`decimate_ground_truth` refuses.
        NotFoundError: no such session.
    """
    kept = decimate_ground_truth(rows)
    done = conn.execute(update(Session).where(Session.id == session_id).values(ground_truth=_blob(kept)))
    if done.rowcount == 0:
        msg = f"no session with id {session_id!r}"
        raise NotFoundError(msg)
    return int(kept.shape[0])


def get_ground_truth(*, conn: Connection, session_id: int) -> npt.NDArray[np.float64] | None:
    """Return a session's ground-truth rows (N × 8), or None when it has none."""
    blob = conn.execute(select(Session.ground_truth).where(Session.id == session_id)).scalar_one_or_none()
    return None if blob is None else _rows(blob)


def ground_truths(*, conn: Connection, session_ids: Collection[int]) -> dict[int, npt.NDArray[np.float64]]:
    """Return ``{session id: rows}`` of the sessions among ``session_ids`` that have ground truth."""
    if not session_ids:
        return {}
    found = conn.execute(
        select(Session.id, Session.ground_truth).where(Session.id.in_(list(session_ids)),
                                                       Session.ground_truth.is_not(None))
    ).all()  # fmt: skip
    return {int(r[0]): _rows(r[1]) for r in found if r[1] is not None}


def session_id_by_name(*, conn: Connection, name: str) -> int:
    """Return the id of the session called ``name``.

    Raises:
        NotFoundError: no such session.
    """
    found = conn.execute(select(Session.id).where(Session.name == name)).scalar_one_or_none()
    if found is None:
        msg = f"no session called {name!r}"
        raise NotFoundError(msg)
    return int(found)

"""A session's ground truth in the store: kept bit for bit (after decimation), replaced, absent until given."""

from __future__ import annotations

import numpy as np
import pytest

from mapserver.errors import NotFoundError
from mapserver.store import Database
from mapserver.store.ground_truth import get_ground_truth, ground_truths, session_id_by_name, set_ground_truth
from mapserver.store.sessions import NewSession, create_session


def test_ground_truth_round_trips_and_is_absent_until_given(db: Database) -> None:
    rows = np.column_stack([100.0 + 0.1 * np.arange(50), np.random.default_rng(1).normal(size=(50, 3)),
                            np.tile([0.0, 0.0, 0.0, 1.0], (50, 1))])  # fmt: skip
    rows[3, 1] = -0.0  # the sign of a zero survives (a blob, not a REAL column)
    with db.write() as conn:
        a = create_session(conn=conn, spec=NewSession(name="a", log_name="a.bag", log_sha256="a" * 64, topics={},
                                                      params={}))  # fmt: skip
        b = create_session(conn=conn, spec=NewSession(name="b", log_name="b.bag", log_sha256="b" * 64, topics={},
                                                      params={}))  # fmt: skip
        assert set_ground_truth(conn=conn, session_id=a.id, rows=rows) == 50  # 10 Hz: every pose kept
    with db.read() as conn:
        got = get_ground_truth(conn=conn, session_id=a.id)
        assert got is not None and got.tobytes() == rows.tobytes()
        assert get_ground_truth(conn=conn, session_id=b.id) is None  # must not: ground truth b was never given
        assert set(ground_truths(conn=conn, session_ids=[a.id, b.id])) == {a.id}
        assert session_id_by_name(conn=conn, name="b") == b.id
        with pytest.raises(NotFoundError):
            session_id_by_name(conn=conn, name="c")
    with db.write() as conn:  # given again: replaced
        assert set_ground_truth(conn=conn, session_id=a.id, rows=rows[:5]) == 5
        with pytest.raises(NotFoundError):
            set_ground_truth(conn=conn, session_id=10_000, rows=rows)
    with db.read() as conn:
        again = get_ground_truth(conn=conn, session_id=a.id)
        assert again is not None and again.shape == (5, 8)

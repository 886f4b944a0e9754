"""``mapserver demo``: the atlas ``make run`` serves — one map built from two simulated sessions by a merge."""

from __future__ import annotations

from pathlib import Path

import pytest

from mapserver.store import open_database
from mapserver.store.merge_events import list_merge_events
from tests.mapserver.merge.scenario_metrics import cli_json

pytestmark = pytest.mark.slow


def test_demo_merges_two_sessions_into_one_map_and_is_built_once(tmp_path: Path) -> None:
    db = f"sqlite:///{tmp_path / 'demo.db'}"
    built = cli_json("demo", "--db", db, "--if-empty")
    assert built["built"] is True
    (demo,) = built["maps"]
    assert (demo["name"], demo["sessions"]) == ("demo", 2)
    with open_database(db) as store, store.read() as conn:
        events = list_merge_events(conn=conn)
    assert [(e.mode, e.status, e.map_name) for e in events] == [("online", "applied", "demo")]
    again = cli_json("demo", "--db", db, "--if-empty")  # make run twice: the atlas is kept, not rebuilt
    assert again == {"built": False, "maps": built["maps"]}

"""Early refusals: every reason an upload's job would fail that is known at upload is a 4xx before 202.

Each refusal is paired with the request that must still pass: a valid name is accepted, a new name once,
and of concurrent uploads of one log under different names the first is queued and proceeds.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from mapserver.api import Settings, create_app
from mapserver.api.jobengine import EmbeddedJobEngine
from mapserver.cli import main
from mapserver.names import check_map_name, default_map_name, is_map_name
from mapserver.store import open_database
from mapserver.store.jobs import count_jobs
from tests.mapserver.api.conftest import Api, api_settings, bearer, make_token
from tests.mapserver.api.logs import write_strip_log
from tests.mapserver.store.conftest import _pg_drop, _pg_schema_url, pg_unreachable

BAD_NAMES = ["a/b", "a%2Fb", ".", "..", "-x", "_x", "a b", "lab\n", "é", "x" * 65, ""]
GOOD_NAMES = ["lab", "Lab-2.v_1", "7", "x" * 64]


def _jobs(api: Api) -> int:
    with open_database(api.db_url) as db, db.read() as conn:
        return sum(count_jobs(conn=conn).values())


def _hold_jobs(api: Api) -> None:
    """Stop the job engine: queued jobs stay queued (pending) until :func:`_run_jobs`."""
    api.client.app.state.services.jobs.stop()  # type: ignore[attr-defined]


def _run_jobs(api: Api) -> None:
    services = api.client.app.state.services  # type: ignore[attr-defined]
    engine = EmbeddedJobEngine(services.db, workers=1, progress_interval_s=0.0)
    engine.start()
    services.jobs = engine


def _log(tmp_path: Path, name: str, seed: int) -> Path:
    return write_strip_log(tmp_path / "logs" / f"{name}.bag", laps=0.6, seed=seed)


def test_the_name_rule_is_one_function() -> None:
    for name in BAD_NAMES:
        assert not is_map_name(name)
        with pytest.raises(Exception, match="invalid map name"):
            check_map_name(name)
    for name in GOOD_NAMES:
        assert is_map_name(name) and check_map_name(name) == name
    assert default_map_name("/logs/my run (2).bag") == "my_run_2_"
    assert default_map_name("/logs/.hidden.bag") == "map"
    assert default_map_name("/logs/" + "r" * 100 + ".bag") == "r" * 56
    assert all(is_map_name(default_map_name(p)) for p in ("a b.bag", "é.db3", "--x.mcap", "x" * 300))


def test_bad_names_are_400_before_any_job_and_good_names_are_accepted(api: Api, tmp_path: Path) -> None:
    log = _log(tmp_path, "names", 4)
    for name in (n for n in BAD_NAMES if n.strip() == n and n):  # the form field is stripped first
        response = api.upload(log, preset="irat", map=name)
        assert response.status_code == 400, (name, response.text)
        assert "invalid map name" in response.json()["detail"]
    assert _jobs(api) == 0
    _hold_jobs(api)
    for k, name in enumerate(GOOD_NAMES):
        other = _log(tmp_path, f"good{k}", 10 + k)
        response = api.upload(other, preset="irat", map=name)
        assert response.status_code == 202, (name, response.text)
        assert response.json()["map"] == name
    assert _jobs(api) == len(GOOD_NAMES)


def test_the_cli_refuses_a_bad_name_and_takes_a_good_one(tmp_path: Path, capsys: Any) -> None:
    log = _log(tmp_path, "cli", 5)
    db_url = f"sqlite:///{tmp_path / 'cli.db'}"
    assert main(["process", str(log), "--preset", "irat", "--db", db_url, "--map", "a/b"]) == 2
    assert "invalid map name 'a/b'" in capsys.readouterr().err
    assert main(["process", str(log), "--preset", "irat", "--db", db_url, "--map", "a-b"]) == 0


def test_an_existing_map_name_is_409_and_a_new_name_is_accepted_once(api: Api, tmp_path: Path) -> None:
    first, second, third = (_log(tmp_path, n, s) for n, s in (("one", 21), ("two", 22), ("three", 23)))
    job = api.upload(first, preset="irat", map="lab", merge="false").json()["job"]
    assert api.wait(job)["status"] == "done"
    refused = api.upload(second, preset="irat", map="lab", merge="false")
    assert refused.status_code == 409, refused.text
    assert "a map named 'lab' exists already" in refused.json()["detail"]
    assert "--map" not in refused.json()["detail"]
    _hold_jobs(api)
    accepted = api.upload(second, preset="irat", map="lab2", merge="false")
    assert accepted.status_code == 202
    # a new name requested by a pending job is taken: a second log asking for it is refused
    taken = api.upload(third, preset="irat", map="lab2", merge="false")
    assert taken.status_code == 409
    assert f"job {accepted.json()['job']} is creating a map named 'lab2'" in taken.json()["detail"]
    assert _jobs(api) == 2
    # the log stored in 'lab' may be uploaded for 'lab' again (it is one of its sessions)
    assert api.upload(first, preset="irat", map="lab", merge="false").status_code == 202


def test_a_log_stored_in_another_map_is_409(api: Api, tmp_path: Path) -> None:
    log = _log(tmp_path, "home", 31)
    job = api.upload(log, preset="irat", map="home", merge="false").json()["job"]
    assert api.wait(job)["status"] == "done"
    refused = api.upload(log, preset="irat", map="elsewhere", merge="false")
    assert refused.status_code == 409
    assert "stored already as session 'home' of map 'home'" in refused.json()["detail"]
    again = api.upload(log, preset="irat", merge="false")  # no map asked for: answered with the stored session
    assert again.status_code == 202
    assert api.wait(again.json()["job"])["status"] == "done"


def test_many_logs_into_one_new_name_queue_one_job(api: Api, tmp_path: Path) -> None:
    _hold_jobs(api)
    logs = [_log(tmp_path, f"many{k}", 40 + k) for k in range(4)]
    statuses = [api.upload(p, preset="irat", map="shared", merge="false").status_code for p in logs]
    assert statuses == [202, 409, 409, 409]
    assert _jobs(api) == 1


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def backend_api(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Api]:
    """An API on SQLite or on a fresh PostgreSQL schema."""
    from fastapi.testclient import TestClient

    schema = None
    if request.param == "postgresql":
        reason = pg_unreachable()
        if reason is not None:
            pytest.skip(reason)
        db_url, schema = _pg_schema_url()
    else:
        db_url = f"sqlite:///{tmp_path / 'api.db'}"
    settings: Settings = api_settings(tmp_path, db_url=db_url)
    client = TestClient(create_app(settings))
    client.__enter__()
    try:
        yield Api(client, db_url, settings, bearer(make_token(db_url, "write")), bearer(make_token(db_url, "read")))
    finally:
        client.__exit__(None, None, None)
        if schema is not None:
            _pg_drop(schema)


def test_concurrent_uploads_of_one_log_under_three_names_queue_one(backend_api: Api, tmp_path: Path) -> None:
    api = backend_api
    _hold_jobs(api)
    log = _log(tmp_path, "same", 51)
    barrier = threading.Barrier(3)
    answers: dict[str, Any] = {}

    def upload(name: str) -> None:
        barrier.wait()
        answers[name] = api.upload(log, preset="irat", map=name, merge="false")

    threads = [threading.Thread(target=upload, args=(n,)) for n in ("red", "green", "blue")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    codes = sorted(a.status_code for a in answers.values())
    assert codes == [202, 409, 409], {n: a.text for n, a in answers.items()}
    winner = next(a.json() for a in answers.values() if a.status_code == 202)
    for loser in (a for a in answers.values() if a.status_code == 409):
        assert f"being processed by job {winner['job']}" in loser.json()["detail"]
    assert _jobs(api) == 1
    _run_jobs(api)  # the first proceeds to the end
    done = api.wait(winner["job"])
    assert done["status"] == "done", done
    assert done["map"] == winner["map"]


def test_rest_answers_name_no_cli_flag(api: Api, strip_log: Path) -> None:
    response = api.upload(strip_log, preset="irat", topics="image")
    assert response.status_code == 400
    assert "topics" in response.json()["detail"] and "--" not in response.json()["detail"]

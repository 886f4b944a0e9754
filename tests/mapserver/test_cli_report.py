"""``mapserver report``: a self-contained HTML report of a stored session or map, with ground truth when given."""

from __future__ import annotations

import base64
import re
from pathlib import Path

import numpy as np
import pytest

from mapserver.cli.demo import DEMO_PARAMS, DEMO_SCENARIO, DEMO_SEED
from mapserver.evaluation import evaluate_map
from mapserver.formats import read_map_json, read_tum
from mapserver.params import resolve_params
from mapserver.processing import pipeline
from mapserver.report import ReportInputs, timeline
from tests.mapserver.merge.scenario_metrics import cli_code, cli_json
from tests.simulations import simulate_once

pytestmark = pytest.mark.slow


def test_report_of_a_session_matches_evaluate_and_embeds_its_figures(tmp_path: Path) -> None:
    scenario = simulate_once(DEMO_SCENARIO, tmp_path / "sim", seed=DEMO_SEED, params=DEMO_PARAMS)
    first = scenario["sessions"][0]
    log, gt_file = tmp_path / "sim" / first["log"], tmp_path / "sim" / first["ground_truth"]
    db = f"sqlite:///{tmp_path / 'r.db'}"
    pipeline.process_into_store(log, resolve_params(scenario["preset"]), db_url=db, map_name="r")
    session = cli_json("maps", "--db", db)["maps"][0]
    assert session["name"] == "r"
    out = tmp_path / "report"
    with_log = cli_json("report", "r", "--db", db, "--out", str(out), "--log", str(log))
    (name, ev), = with_log["evaluation"].items()  # fmt: skip
    # independent path: the map exported as JSON, evaluated against the simulator's TUM ground truth
    cli_json("export", "--db", db, "--map", "r", "--format", "json", "--out", str(tmp_path / "r.json"))
    expected = evaluate_map(read_map_json(tmp_path / "r.json"), read_tum(gt_file), session=name)
    assert ev["ape_rmse"] == pytest.approx(expected["ape_rmse"], rel=1e-6)
    assert ev["hausdorff"] == pytest.approx(expected["hausdorff"], rel=1e-6)
    page = Path(with_log["report"]).read_text()
    assert f"{ev['ape_rmse']:.3f}" in page and f"{ev['hausdorff']:.3f}" in page
    embedded = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert len(embedded) == 3 == len(with_log["pngs"])  # map, timeline, trajectory vs ground truth
    assert all(base64.b64decode(b)[:8] == b"\x89PNG\r\n\x1a\n" for b in embedded)
    assert sorted(Path(p).name for p in with_log["pngs"]) == ["ground_truth_1.png", "map.png", "timeline.png"]
    assert "<script" not in page and "http" not in page.replace("http-equiv", "")  # self-contained

    # without ground truth: still a report, and it says what is missing
    bare = cli_json("report", name, "--db", db, "--out", str(tmp_path / "bare"))
    assert bare["evaluation"] == {} and "No ground truth" in Path(bare["report"]).read_text()
    code, err = cli_code("report", "nothing-called-this", "--db", db, "--out", str(tmp_path / "x"))
    assert code == 2 and "no map or session named" in err


def test_timeline_marks_the_first_use_of_each_template_as_new() -> None:
    rows = [(0, 0, "a"), (1, 1, "a"), (2, 0, "a"), (3, 2, "a"), (0.5, 1, "b")]
    exps = [{"id": i, "stamp": float(t), "template": z, "session": s} for i, (t, z, s) in enumerate(rows)]
    doc = {"experiences": exps, "links": [], "sessions": [{"name": "a"}, {"name": "b"}], "templates": 3}
    series = timeline(ReportInputs("m", None, doc, [], []))
    # by stamp: (0, t0 new), (0.5, t1 new: b), (1, t1 recognised), (2, t0 recognised), (3, t2 new)
    assert series["template"].tolist() == [0, 1, 1, 0, 2]
    assert series["new"].tolist() == [True, True, False, False, True]
    only_a = timeline(ReportInputs("m", "a", doc, [], []))
    assert only_a["id"].tolist() == [0, 1, 2, 3] and only_a["new"].tolist() == [True, False, False, True]
    assert np.all(np.diff(only_a["stamp"]) > 0)


def test_the_stored_timeline_has_every_frame_by_template_identity_and_resumes_exactly(tmp_path: Path) -> None:
    """Issue 16 (OpenRatSLAM2 Fig. 6): every frame's active template is stored with the session and resolved
    to the map's ids after the merge; session 2 recognises session 1's templates; a split run stores the same
    timeline as one run."""
    from core import Engine
    from mapserver.report import gather
    from mapserver.store import open_database

    scenario = simulate_once(DEMO_SCENARIO, tmp_path / "sim", seed=DEMO_SEED, params=DEMO_PARAMS)
    params = resolve_params(scenario["preset"])
    logs = [tmp_path / "sim" / s["log"] for s in scenario["sessions"]]
    db = f"sqlite:///{tmp_path / 't.db'}"
    results = [pipeline.process_into_store(log, params, db_url=db) for log in logs]
    assert len(results[1].merges) == 1
    with open_database(db) as handle:
        inputs = gather(handle, results[1].map_name)
    first, second = (inputs.activations[s["name"]] for s in scenario["sessions"])
    assert first[0].shape[0] == results[0].frames and second[0].shape[0] == results[1].frames
    # independent: session 1 alone through the engine, frame by frame (its map's ids are the engine's)
    seen: list[tuple[int, bool]] = []
    pipeline.run_engine(Engine(params), logs[0], on_step=lambda _f, r: seen.append((r.template, r.template_created)))
    assert first[0][:, 1].astype(int).tolist() == [t for t, _ in seen]
    assert first[1].tolist() == [c for _, c in seen]
    stored_templates = int(first[1].sum())
    recognised = (~second[1]) & (second[0][:, 1] >= 0) & (second[0][:, 1] < stored_templates)
    assert recognised.sum() > 0.5 * second[0].shape[0]  # session 2 re-drives session 1's ground
    # the timeline of a split run equals one run
    split = f"sqlite:///{tmp_path / 's.db'}"
    pipeline.process_into_store(logs[0], params, db_url=split, stop_after=results[0].frames // 2)
    pipeline.process_into_store(logs[0], params, db_url=split)
    with open_database(split) as handle:
        again = gather(handle, results[0].map_name).activations[scenario["sessions"][0]["name"]]
    assert np.array_equal(again[0], first[0]) and np.array_equal(again[1], first[1])

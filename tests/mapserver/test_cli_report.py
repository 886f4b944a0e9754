"""``mapserver report``: a self-contained HTML report of a stored session or map, with ground truth when given."""

from __future__ import annotations

import base64
import re
from pathlib import Path

import numpy as np
import pytest

from mapserver import pipeline
from mapserver.cli.demo import DEMO_PARAMS, DEMO_SCENARIO, DEMO_SEED
from mapserver.evaluation import evaluate_map
from mapserver.formats import read_map_json, read_tum
from mapserver.ingest.simulator import simulate
from mapserver.params import resolve_params
from mapserver.report import ReportInputs, timeline
from tests.mapserver.merge.scenario_metrics import cli_code, cli_json

pytestmark = pytest.mark.slow


def test_report_of_a_session_matches_evaluate_and_embeds_its_figures(tmp_path: Path) -> None:
    scenario = simulate(DEMO_SCENARIO, tmp_path / "sim", seed=DEMO_SEED, params=DEMO_PARAMS)
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

"""Where the robust check stops catching a wrong manual link: a sweep of the link's stated error.

The map is the blind `loop` of ``tests/mapserver/test_manual_links.py`` (half scale, 1.25 laps, no view ever
matched: 87 experiences, the odometry's map). One manual link joins experience 0 to 69 (the start, one lap
later) with the ground truth's transform plus an error of ``offset`` metres along x. For each offset: whether the
link stayed on, its misfit after settling, and the map's APE. Prints one JSON line.

    PYTHONPATH=$PWD .venv/bin/python bench/manual_link_sweep.py [--offsets 0,0.5,1,2,3,5,10,20] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

from mapserver.atlas.manual_links import LinkRequest, link_experiences
from mapserver.formats import read_tum
from mapserver.processing import pipeline
from mapserver.store import open_database
from tests.mapserver.test_manual_links import BLIND, LAP_END, LAP_START, _ape, _stated
from tests.simulations import simulate_once


def sweep(work: Path, offsets: list[float]) -> dict[str, object]:
    """Link 0 → 69 once per offset, each on a fresh copy of the blind map; return the rows."""
    simulate_once("loop", work, scale=0.5, params={"laps": 1.25}, only=["single"])
    base = work / "blind.db"
    base.unlink(missing_ok=True)
    pipeline.process_into_store(work / "single.bag", BLIND, db_url=f"sqlite:///{base}", map_name="blind")
    truth = read_tum(work / "single.tum")
    rows = []
    for offset in offsets:
        copy = work / f"offset-{offset}.db"
        shutil.copy(base, copy)
        url = f"sqlite:///{copy}"
        stated = list(_stated(url, truth, "blind", LAP_START, LAP_END))
        stated[0] += offset
        with open_database(url) as db:
            outcome = link_experiences(db, LinkRequest("blind", LAP_START, LAP_END, transform=tuple(stated),  # type: ignore[arg-type]
                                                       author="bench"))  # fmt: skip
        rows.append({"offset_m": offset, "active": bool(outcome.active), "misfit_m": round(float(outcome.misfit_m), 3),
                     "ape_m": round(_ape(url, "blind", truth), 3)})  # fmt: skip
    return {"odometry_ape_m": round(_ape(f"sqlite:///{base}", "blind", truth), 3), "rows": rows}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--offsets", default="0,0.25,0.5,1,1.5,2,3,5,10,20")
    parser.add_argument("--work", type=Path, default=None)
    args = parser.parse_args()
    offsets = [float(v) for v in args.offsets.split(",")]
    with tempfile.TemporaryDirectory() as temp:
        print(json.dumps(sweep(args.work or Path(temp), offsets)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

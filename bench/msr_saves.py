"""Import every save of multisession-ratslam's repository, and compare our merge of its circle maps with its own.

Usage: python bench/msr_saves.py SAVES [--db URL]

SAVES is a local copy of ``ratslam/Saves`` from MatheusMenezes/multisession-ratslam (not part of this
repository; e.g. ``git --git-dir=MIRROR archive HEAD ratslam/Saves | tar -x -C /tmp``). Every directory
holding an ``experiences.txt`` is imported with ``mapserver import DIR --format multisession-ratslam``,
with the parameters of the tool's configuration that its ``TEMPLATE_SIZE`` names (``--preset circle`` for
4096 = 128 × 32; a YAML ``--config`` with the template size and lattice for the others, read from the
tool's ``_globals_*.py``; 600 and 640 match none of them and are read as 60 × 10 and 64 × 10 with the
lattice the saved pose-cell coordinates span).

Then ``mapserver merge --map circle_partial --into circle_loaded --confirm 1 --merge-evidence 0`` (the tool
merges on one matching frame: the paper's rule, without our evidence test) and the merged map is compared with
the tool's own ``circle_merged``, experience by experience (both number the loaded map's experiences first,
then the partial map's): counts, and the position RMSE after rigid alignment (Umeyama, no scale, xy) as a
share of the diagonal of ``circle_merged``'s bounding box. The tool saved ``circle_merged`` while it went on
mapping after the merge (main-circle.py saves at frames 138–394 of its video): its one link that our merged
map lacks is the loop closure it made then. A second figure adds that one link (its measured transform, read
from ``circle_merged``) to our merged map and settles the graph. Last line of stdout: one JSON object.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from core import Engine, preset
from mapserver.cli import main
from mapserver.evaluation import ape_positions
from mapserver.store import load_map, open_database

# TEMPLATE_SIZE -> (template_x_size, template_y_size, pc_dim_xy, pc_dim_th)
FAMILIES = {
    1500: (50, 30, 11, 36),  # _globals_irat.py
    4800: (80, 60, 80, 36),  # _globals_lacmor.py
    320: (32, 10, 60, 36),  # _globals.py
    600: (60, 10, 80, 36),
    640: (64, 10, 30, 36),
}
LINK_KEYS = ("em_link_from", "em_link_to", "em_link_transform", "em_link_dt", "em_link_distance", "em_link_kind")


def _params_args(directory: Path, folder: Path) -> list[str]:
    lvc = directory / "localviewcells.txt"
    first = lvc.read_text(encoding="utf-8").split("\n", 1)[0].strip() if lvc.is_file() else ""
    size = int(float(first)) if first else 4096
    if size == 4096:
        return ["--preset", "circle"]
    tx, ty, dim_xy, dim_th = FAMILIES[size]
    config = folder / f"params_{size}.yaml"
    config.write_text(
        f"template_x_size: {tx}\ntemplate_y_size: {ty}\npc_dim_xy: {dim_xy}\npc_dim_th: {dim_th}\n", encoding="utf-8"
    )
    return ["--config", str(config)]


def import_all(saves: Path, db_url: str, folder: Path) -> list[dict[str, Any]]:
    """Import every save directory under ``saves``; return one row per directory (ok, counts or error)."""
    rows = []
    for directory in sorted({p.parent for p in saves.rglob("experiences.txt")}):
        name = str(directory.relative_to(saves)).replace("/", "__")
        argv = ["import", str(directory), "--db", db_url, "--format", "multisession-ratslam", "--map", name]
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main([*argv, *_params_args(directory, folder), "--json"])
        row: dict[str, Any] = {"save": str(directory.relative_to(saves)), "exit": code}
        if code == 0:
            row |= {k: v for k, v in json.loads(out.getvalue().splitlines()[-1]).items() if k != "notes"}
        else:
            row["error"] = err.getvalue().strip().splitlines()[-1]
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def _rmse_share(reference: np.ndarray, estimate: np.ndarray, extent: float) -> dict[str, float]:
    result = ape_positions(reference, estimate)
    return {"rmse_m": result.rmse, "rmse_share": result.rmse / extent, "max_share": result.max / extent}


def compare_circle(db_url: str) -> dict[str, Any]:
    """Merge circle_partial into circle_loaded and compare with the tool's circle_merged."""
    argv = ["merge", "--db", db_url, "--map", "circle_partial", "--into", "circle_loaded", "--confirm", "1",
            "--merge-evidence", "0"]  # fmt: skip
    if main(argv) != 0:
        return {"merged": False}
    with open_database(db_url) as db:
        ours = load_map(db, name="circle_loaded").snapshot
        tool = load_map(db, name="circle_merged").snapshot
    reference = np.asarray(tool["em_pose"])[:, :2]
    extent = float(np.linalg.norm(reference.max(axis=0) - reference.min(axis=0)))
    result: dict[str, Any] = {
        "experiences": [int(ours["em_pose"].shape[0]), int(tool["em_pose"].shape[0])],
        "templates": [int(ours["lv_templates"].shape[0]), int(tool["lv_templates"].shape[0])],
        "links": [int(ours["em_link_from"].shape[0]), int(tool["em_link_from"].shape[0])],
        "extent_m": extent,
    }
    if result["experiences"][0] != result["experiences"][1]:
        return result
    result["merge"] = _rmse_share(reference, np.asarray(ours["em_pose"])[:, :2], extent)
    ours_pairs = set(zip(ours["em_link_from"].tolist(), ours["em_link_to"].tolist(), strict=True))
    missing = [
        j
        for j, pair in enumerate(zip(tool["em_link_from"].tolist(), tool["em_link_to"].tolist(), strict=True))
        if pair not in ours_pairs
    ]
    result["links_only_in_tool"] = [[int(tool["em_link_from"][j]), int(tool["em_link_to"][j])] for j in missing]
    state = {k: np.array(v) for k, v in ours.items()}
    for key in LINK_KEYS:
        state[key] = np.concatenate([state[key], np.asarray(tool[key])[missing]])
    engine = Engine.restore(preset("circle"), state)
    engine.settle()
    settled = engine.snapshot()["em_pose"][:, :2]
    result["merge_plus_tool_links_settled"] = _rmse_share(reference, settled, extent)
    return result


def run(saves: Path, db_url: str | None) -> dict[str, Any]:
    """Import all saves, compare the circle merge; return the summary."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        url = db_url or f"sqlite:///{folder / 'saves.db'}"
        rows = import_all(saves, url, folder)
        circle = (
            compare_circle(url)
            if {"circle_loaded", "circle_partial", "circle_merged"} <= {r["save"] for r in rows if r["exit"] == 0}
            else None
        )
    return {"imported": sum(r["exit"] == 0 for r in rows), "saves": len(rows), "circle": circle}


def cli() -> None:
    """Parse the arguments, run, print the JSON summary last."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("saves", type=Path, help="local copy of multisession-ratslam's ratslam/Saves")
    parser.add_argument("--db", help="database URL (default: a temporary SQLite file)")
    args = parser.parse_args()
    print(json.dumps(run(args.saves, args.db)))


if __name__ == "__main__":
    cli()

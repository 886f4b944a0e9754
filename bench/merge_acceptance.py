"""Issue 5 acceptance figures at full scale, measured with the contract's commands (the README's table).

Usage: python bench/merge_acceptance.py [--out DIR] [--seed 0]

Simulates ellipse (default, ``--merge-no-shift``, session 2 turned 90°), bridge, chain5, cave3d and
aliased into DIR, processes their sessions into SQLite databases there with ``mapserver process --db``
and prints the figures the acceptance tests (tests/mapserver/merge/test_acceptance.py) bound. The last
line of stdout is one JSON object with every figure.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the tests' measuring helpers

from tests.mapserver.merge.scenario_metrics import cli_json, load_doc, measure_ellipse


def _simulate(out: Path, name: str, seed: int, **params: float) -> tuple[Path, dict[str, Any]]:
    tag = name + "".join(f"-{k}{v:g}" for k, v in params.items())
    directory = out / tag
    argv = ["simulate", name, "--out", str(directory), "--seed", str(seed)]
    if params:
        argv += ["--param", ",".join(f"{k}={v}" for k, v in params.items())]
    return directory, cli_json(*argv)


def _ellipse(out: Path, seed: int) -> dict[str, Any]:
    figures: dict[str, Any] = {}
    directory, info = _simulate(out, "ellipse", seed)
    single_json = directory / "single-map.json"
    cli_json("process", str(directory / info["single"]["log"]), "--out", str(single_json))
    single = load_doc(single_json)
    variants = {"default": (directory, ()), "no_shift": (directory, ("--merge-no-shift",)),
                "turned_90": (_simulate(out, "ellipse", seed, heading_offset_deg=90.0)[0], ())}  # fmt: skip
    for name, (folder, extra) in variants.items():
        m = measure_ellipse(folder, f"sqlite:///{folder / f'{name}.db'}", *extra, single=single)
        figures[name] = {
            "merges": len(m["merges"]),
            "merge_frame": m["merges"][0]["frame"] if m["merges"] else None,
            "transform_error_m_rad": [round(v, 3) for v in m["transform_error"]],
            "s1_path_frames": m["s1_path"].frames,
            "s1_path_created": m["s1_path"].created,
            "s1_path_rate": round(m["s1_path"].rate, 4),
            "own_path_frames": m["own_path"].frames,
            "own_path_created": m["own_path"].created,
            "partial_experiences": m["own_experiences"],
            "experiences": m["experiences"],
            "single_experiences": m["single_experiences"],
            "count_ratio": round(m["experiences"] / m["single_experiences"], 3),
            "rmse_m": round(m["rmse"], 3),
            "extent_m": round(m["extent"], 2),
            "rmse_over_extent": round(m["rmse"] / m["extent"], 4),
        }
        print(name, figures[name], flush=True)
    return figures


def _sessions(directory: Path, info: dict[str, Any], db: str, *extra: str) -> list[dict[str, Any]]:
    return [cli_json("process", str(directory / s["log"]), "--db", db, *extra) for s in info["sessions"]]


def main() -> None:
    """Run every scenario and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", help="work directory (default: a temporary one)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    out = Path(args.out or tempfile.mkdtemp(prefix="merge-acceptance-"))
    started = time.perf_counter()
    figures: dict[str, Any] = {"ellipse": _ellipse(out, args.seed)}
    for name in ("bridge", "chain5"):
        directory, info = _simulate(out, name, args.seed)
        db = f"sqlite:///{directory / 'atlas.db'}"
        results = _sessions(directory, info, db)
        maps = cli_json("maps", "--db", db)["maps"]
        doc = directory / "map.json"
        cli_json("export", "--db", db, "--map", maps[0]["name"], "--format", "json", "--out", str(doc))
        exps = load_doc(doc)["experiences"]
        first = {s: min(e["id"] for e in exps if e["session"] == s) for s in sorted({e["session"] for e in exps})}
        paths = {}
        for other in sorted(first)[1:]:
            found = cli_json("path", "--db", db, "--map", maps[0]["name"], "--from", str(first["session1"]),
                             "--to", str(first[other]), "--weight", "distance")  # fmt: skip
            paths[other] = {"nodes": len(found["nodes"]), "metres": round(found["cost"], 1)}
        figures[name] = {"maps": [(m["name"], m["sessions"], m["experiences"]) for m in maps],
                         "merges": [[(x["into"], x["frame"]) for x in r["merges"]] for r in results],
                         "paths_from_session1": paths}  # fmt: skip
        print(name, figures[name], flush=True)
    directory, info = _simulate(out, "cave3d", args.seed)
    db = f"sqlite:///{directory / 'atlas.db'}"
    results = _sessions(directory, info, db, "--preset", "poseidon")
    merged, single = directory / "merged.json", directory / "single-map.json"
    cli_json("export", "--db", db, "--map", "session1", "--format", "json", "--out", str(merged))
    cli_json("process", str(directory / info["single"]["log"]), "--preset", "poseidon", "--out", str(single))
    both = directory / "both.tum"
    both.write_text("".join((directory / s["ground_truth"]).read_text() for s in info["sessions"]))
    radii = ("--revisit-radius", "0.3", "--match-radius", "0.6", "--false-radius", "1.0")
    m = cli_json("evaluate", str(merged), "--ground-truth", str(both), *radii)
    s = cli_json("evaluate", str(single), "--ground-truth", str(directory / info["single"]["ground_truth"]), *radii)
    figures["cave3d"] = {
        "merges": [len(r["merges"]) for r in results],
        "merged_ape_m": round(m["ape_rmse"], 3), "merged_ape_z_m": round(m["ape_z_rmse"], 3),
        "single_ape_m": round(s["ape_rmse"], 3), "single_ape_z_m": round(s["ape_z_rmse"], 3),
    }  # fmt: skip
    print("cave3d", figures["cave3d"], flush=True)
    directory, info = _simulate(out, "aliased", args.seed)
    careful = _sessions(directory, info, f"sqlite:///{directory / 'k-default.db'}")
    eager = _sessions(directory, info, f"sqlite:///{directory / 'k1.db'}", "--confirm", "1", "--merge-evidence", "0",
                      "--merge-probation", "0")  # the paper's single-frame trigger  # fmt: skip
    figures["aliased"] = {"default_k_merges": sum(len(r["merges"]) for r in careful),
                          "k1_merges": sum(len(r["merges"]) for r in eager)}  # fmt: skip
    print("aliased", figures["aliased"], flush=True)
    figures["seconds"] = round(time.perf_counter() - started, 1)
    print(json.dumps(figures))


if __name__ == "__main__":
    main()

"""Map store throughput: save and load seconds for a large map on SQLite (issue 4 target: save ≤ 5 s, load ≤ 3 s).

Usage: python bench/store.py [--experiences 100000] [--links 200000] [--templates 20000] [--preset irat]
                             [--repeat 3] [--db URL]

Builds a synthetic engine snapshot of that size (templates of the preset's size, one LVC→pose-cell link
per template, a chain of odometry links plus random loop links, a tenth of them switched off by the robust
check, a tenth of the experiences with a merge's lever arm), then, ``--repeat`` times, saves it as a
new map in a fresh SQLite file (one transaction: map, session, templates, pose-cell links, experiences,
links, state) and loads it back, checking the round trip is exact. Prints one line per run and, last, one
JSON object: {"experiences", "links", "templates", "template_shape", "save_s", "load_s"} (best runs) with
every run's figures.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from core import Engine, LinkKind, preset
from mapserver.store import NewSession, load_map, open_database, save_map


def synthetic_snapshot(
    experiences: int, links: int, templates: int, preset_name: str, seed: int = 0
) -> tuple[object, dict[str, np.ndarray]]:
    """Return (params, snapshot) of a map of the given size; every other key is a fresh engine's."""
    params = preset(preset_name)
    rng = np.random.default_rng(seed)
    snap = Engine(params).snapshot()
    ty, tx = params.template_y_size, params.template_x_size
    rank = snap["pc_activity"].ndim
    dims = np.asarray(snap["pc_activity"].shape, dtype=np.float64)
    lv = rng.random((templates, ty, tx), dtype=np.float32)
    snap["lv_templates"] = lv
    snap["lv_means"] = lv.reshape(templates, -1).mean(axis=1, dtype=np.float64)
    snap["lv_origin"] = np.zeros(templates, dtype=np.int64)
    snap["pc_link_template"] = np.arange(templates, dtype=np.int64)
    snap["pc_link_coords"] = rng.random((templates, rank)) * dims
    snap["pc_link_strength"] = np.ones(templates)
    snap["pc_link_decay"] = rng.random(templates)
    steps = rng.normal(0, 0.3, size=(experiences, 4))
    steps[:, 2] = 0.0
    snap["em_pose"] = np.cumsum(steps, axis=0)
    snap["em_pc"] = rng.random((experiences, rank)) * dims
    snap["em_template"] = rng.integers(0, templates, size=experiences, dtype=np.int64)
    snap["em_stamp"] = np.arange(experiences, dtype=np.float64) * 0.5
    snap["em_origin"] = np.zeros(experiences, dtype=np.int64)
    chain = min(experiences - 1, links)
    loops = links - chain
    src = np.concatenate([np.arange(chain), rng.integers(0, experiences, size=loops)]).astype(np.int64)
    dst = np.concatenate([np.arange(1, chain + 1), rng.integers(0, experiences, size=loops)]).astype(np.int64)
    snap["em_link_from"] = src
    snap["em_link_to"] = dst
    snap["em_link_transform"] = rng.normal(0, 0.3, size=(links, 4))
    snap["em_link_dt"] = rng.random(links)
    snap["em_link_distance"] = rng.random(links)
    snap["em_link_kind"] = np.repeat(np.array([LinkKind.ODOMETRY, LinkKind.LOOP], dtype=np.int8), [chain, loops])
    # one entry per experience and per link, as an engine's snapshot has them (the store fits shorter ones to
    # the rows, lever 0 and link on, so an empty engine's (0,) arrays would not come back as they went in)
    snap["em_pc_lever"] = np.where(rng.random(experiences) < 0.1, rng.random(experiences), 0.0)
    snap["em_link_active"] = (snap["em_link_kind"] == LinkKind.ODOMETRY) | (rng.random(links) < 0.9)
    snap["em_current"] = np.asarray(experiences - 1, dtype=np.int64)
    snap["lv_current"] = np.asarray(templates - 1, dtype=np.int64)
    return params, snap


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiences", type=int, default=100_000)
    parser.add_argument("--links", type=int, default=200_000)
    parser.add_argument("--templates", type=int, default=20_000)
    parser.add_argument("--preset", default="irat")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--db", help="database URL (default: a fresh SQLite file per run in a temp directory)")
    args = parser.parse_args()

    params, snap = synthetic_snapshot(args.experiences, args.links, args.templates, args.preset)
    shape = list(snap["lv_templates"].shape[1:])
    runs = []
    with tempfile.TemporaryDirectory(prefix="mapserver-bench-") as tmp:
        for run in range(args.repeat):
            url = args.db or f"sqlite:///{Path(tmp) / f'bench{run}.db'}"
            with open_database(url) as db:
                session = NewSession(
                    name=f"bench-{run}-{time.time_ns()}",
                    log_name="bench.bag",
                    log_sha256=f"{run:064x}",
                    topics={"image": "/camera", "run": str(time.time_ns())},
                    params=params.to_dict(),
                    frames_processed=args.experiences,
                )
                name = f"bench-{run}-{time.time_ns()}"
                start = time.perf_counter()
                save_map(db, name=name, params=params, snapshot=snap, sessions=[session])
                save_s = time.perf_counter() - start
                start = time.perf_counter()
                content = load_map(db, name=name)
                load_s = time.perf_counter() - start
            differ = [
                k
                for k, v in snap.items()
                if content.snapshot[k].dtype != v.dtype
                or content.snapshot[k].shape != v.shape
                or not (k.endswith("_origin") or content.snapshot[k].tobytes() == v.tobytes())
            ]
            exact = not differ
            runs.append({"save_s": round(save_s, 3), "load_s": round(load_s, 3), "exact": exact})
            print(f"run {run + 1}: save {save_s:.3f} s, load {load_s:.3f} s, exact round trip: {exact}"
                  + (f" (differ: {', '.join(differ)})" if differ else ""))  # fmt: skip
    result = {
        "experiences": args.experiences,
        "links": args.links,
        "templates": args.templates,
        "template_shape": shape,
        "save_s": min(r["save_s"] for r in runs),
        "load_s": min(r["load_s"] for r in runs),
        "runs": runs,
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()

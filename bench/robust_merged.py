"""Wrong loop links injected into *merged* maps: the robust check with and without ``merge_relax_joint``.

Usage: python bench/robust_merged.py [--out DIR] [--seeds 5] [--sizes 0.5,1,2,5] [--counts 1,5,20]
[--maps cave3d:0:poseidon,symmetric:0:circle,twin-overlap:3:circle] [--no-ties] [--no-view-heading]

``bench/robust_relaxation.py`` injects into single-session maps, which ``merge_relax_joint`` leaves alone. Here
each ``SCENARIO:SEED:PRESET`` is simulated and both sessions are processed into one database with the contract's
commands (``mapserver simulate``, ``mapserver process --db``), so session 2 merges into session 1's map; the
merged map is then loaded and, for every k and size (how far apart in metres the two experiences a wrong link
joins really are) and injection seed, k wrong loop links (``core.robust.false_loop_links``) are added and the map
settled, once with ``merge_relax_joint`` off and once on. Prints per row the APE ratio against the same map
settled without injection (median and max over seeds), whether the row meets issue 12's bound (max ≤ 1.25), and
how far apart in the world the wrong links' ends are (median), against the map's own loop and merge links: the share
of wrong links no farther apart than the farthest true one, which the graph's consistency cannot tell from it.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the tests' measuring helpers

from core import Engine, LinkKind
from core.robust import false_loop_links
from tests.mapserver.robust_metrics import (
    Simulated,
    closure_range,
    closure_separation,
    map_ape,
    separation_figures,
    simulate_merged,
    world_separation,
)


def settled_ape(merged: Simulated, joint: bool, count: int, size: float, seed: int) -> tuple[float, np.ndarray]:
    """APE of the map settled after ``count`` wrong links of ``size`` metres (injection ``seed``), and how far apart
    in the world the experiences each wrong link joins are."""
    engine = Engine.restore(merged.params.replace(merge_relax_joint=joint), merged.state)
    src, dst, transform = false_loop_links(engine.map.poses, count, size, seed)
    for a, b, t in zip(src.tolist(), dst.tolist(), transform, strict=True):
        engine.map.add_link_raw(a, b, t, 1.0, float(np.linalg.norm(t[:3])), LinkKind.LOOP)
    engine.settle()
    return map_ape(engine.map.poses, engine.snapshot()["em_stamp"], merged.truth), world_separation(merged, src, dst)


def main() -> None:
    """Print one table per merged map and setting, then one JSON object."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--sizes", default="0.5,1,2,5")
    parser.add_argument("--counts", default="1,5,20")
    parser.add_argument("--maps", default="cave3d:0:poseidon,symmetric:0:circle,twin-overlap:3:circle")
    parser.add_argument("--no-ties", action="store_true",
                        help="merge without the ties of the winning hypothesis's hits (the maps before 2026-11-29)")
    parser.add_argument("--no-view-heading", action="store_true",
                        help="merge_view_heading=0: closures and ties between the sessions carry no view heading")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="robust-merged-"))
    rows = []
    for spec in args.maps.split(","):
        scenario, seed, preset = spec.split(":")
        merged = simulate_merged(out / f"{scenario}-{seed}", scenario, int(seed), preset, tie_hits=not args.no_ties,
                                 view_heading=not args.no_view_heading)  # fmt: skip
        own = closure_separation(merged)
        for joint in (False, True):
            clean = settled_ape(merged, joint, 0, 0.0, 0)[0]
            print(f"{scenario} seed {seed} ({preset}), merge_relax_joint={int(joint)}: clean APE {clean:.3f} m; "
                  f"its {own.size} closures join places {closure_range(own)} apart")  # fmt: skip
            for count in (int(c) for c in args.counts.split(",")):
                for size in (float(s) for s in args.sizes.split(",")):
                    runs = [settled_ape(merged, joint, count, size, s) for s in range(args.seeds)]
                    ratio = [ape / clean for ape, _ in runs]
                    apart_m, within = separation_figures(np.concatenate([a for _, a in runs]), own)
                    ok = max(ratio) <= 1.25
                    print(f"   k {count:2d}  size {size:4.1f} m  APE ratio med {statistics.median(ratio):.2f} "
                          f"max {max(ratio):.2f}  {'ok' if ok else 'FAIL'}  wrong links apart med {apart_m:.2f} m, "
                          f"{within:.0%} within the closures' range")  # fmt: skip
                    rows.append({"map": spec, "joint": joint, "k": count, "size_m": size, "clean_m": clean,
                                 "ratio": ratio, "ok": ok, "within_closures": within})  # fmt: skip
            sys.stdout.flush()
    print(json.dumps({"rows": rows}))


if __name__ == "__main__":
    main()

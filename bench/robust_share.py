"""The robust check's share of a run: CPU seconds inside ``core.robust.switch_off_outliers`` against the whole run.

Usage: python bench/robust_share.py SCRIPT [ARGS...]
       python bench/robust_share.py bench/core_throughput.py --preset irat --templates 5000
       python bench/robust_share.py mapserver process LOG --config INI --out map.json

Runs SCRIPT (or the ``mapserver`` command line) in this process with the engine's robust check
(:meth:`core.experience_map.ExperienceMap.check_links` → ``switch_off_outliers``) timed by
``time.process_time``, and after it ends prints one line to stderr and the last stdout line, one JSON object:
{"robust_s", "total_s", "share", "checks", "hypotheses"} (CPU seconds of the checks and of the whole run from
this script's start, the checks' share, how many checks ran and how many hypotheses, relaxation states
scored, they tried). A share taken in one process is what a busy machine slows alike in both.
"""

from __future__ import annotations

import atexit
import json
import runpy
import sys
import time
from typing import Any

import core.experience_map as experience_map

_started = time.process_time()
_spent = {"robust_s": 0.0, "checks": 0, "hypotheses": 0}
_check = experience_map.switch_off_outliers


def _timed(*args: Any, **kwargs: Any) -> Any:
    begun = time.process_time()
    result = _check(*args, **kwargs)
    _spent["robust_s"] += time.process_time() - begun
    _spent["checks"] += 1
    _spent["hypotheses"] += result.iterations
    return result


def _report() -> None:
    total = time.process_time() - _started
    row = {"robust_s": round(_spent["robust_s"], 3), "total_s": round(total, 3),
           "share": round(_spent["robust_s"] / total, 4) if total > 0 else 0.0,
           "checks": _spent["checks"], "hypotheses": _spent["hypotheses"]}  # fmt: skip
    print(f"robust check: {row['robust_s']:.2f} s of {row['total_s']:.2f} s CPU ({100 * row['share']:.1f} %), "
          f"{row['checks']} checks, {row['hypotheses']} hypotheses", file=sys.stderr)  # fmt: skip
    print(json.dumps(row))


def main() -> None:
    """Run the script or module named on the command line with the robust check timed."""
    if len(sys.argv) < 2:
        raise SystemExit(__doc__)
    experience_map.switch_off_outliers = _timed
    atexit.register(_report)
    if sys.argv[1] == "mapserver":
        from mapserver.cli import main as command

        code = command(sys.argv[2:])
        if code:
            raise SystemExit(code)
    else:
        sys.argv = sys.argv[1:]
        runpy.run_path(sys.argv[0], run_name="__main__")


if __name__ == "__main__":
    main()

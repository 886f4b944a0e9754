"""A Celery worker process runs each job on one core: its numeric libraries get one thread each (issue 15)."""

from __future__ import annotations

import json
import subprocess
import sys

PROBE = """
import json, cv2
from threadpoolctl import threadpool_info
before = {"cv2": cv2.getNumThreads(), "blas": [p["num_threads"] for p in threadpool_info()]}
from mapserver.api.celery_worker import one_core_per_job
one_core_per_job()
after = {"cv2": cv2.getNumThreads(), "blas": [p["num_threads"] for p in threadpool_info()]}
print(json.dumps({"before": before, "after": after}))
"""


def test_one_core_per_job_limits_every_pool_to_one_thread() -> None:
    env = {"PATH": "/usr/bin:/bin", "OPENBLAS_NUM_THREADS": "2", "OMP_NUM_THREADS": "2"}  # a 2-thread start
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, check=True)
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    assert max(seen["before"]["blas"]) == 2  # the probe starts with pools of 2: the change below is the function's
    assert seen["after"]["blas"] and all(n == 1 for n in seen["after"]["blas"])
    assert seen["after"]["cv2"] == 1

"""Every service runs its BLAS on one thread (shared/service.py `one_blas_thread`)."""

from __future__ import annotations

import json
import subprocess
import sys

from shared.paths import REPO_ROOT

PROBE = """
import json

from threadpoolctl import threadpool_info
from shared.service import one_blas_thread
one_blas_thread()
print(json.dumps([i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]))
"""


def test_numpy_and_scipy_blas_run_on_one_thread() -> None:
    # A fresh interpreter: the limit applies to the libraries loaded in the process that sets it.
    probe = [sys.executable, "-c", PROBE]
    out = subprocess.run(probe, cwd=REPO_ROOT, capture_output=True, text=True, check=True)
    threads = json.loads(out.stdout)
    assert len(threads) >= 2 and set(threads) == {1}, threads  # NumPy's and SciPy's OpenBLAS

"""Every service runs its BLAS on one thread (shared/service.py `one_blas_thread`)."""

from __future__ import annotations

import subprocess
import sys

from shared.paths import REPO_ROOT

PROBE = """
from threadpoolctl import threadpool_info
from shared.service import one_blas_thread
one_blas_thread()
print(json.dumps([i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]))
"""


def test_numpy_and_scipy_blas_run_on_one_thread() -> None:
    # A fresh interpreter: the limit applies to the libraries loaded in the process that sets it.
    out = subprocess.run(
        [sys.executable, "-c", PROBE], cwd=REPO_ROOT, capture_output=True, text=True, check=True
    )
    found = eval(out.stdout)
    assert found and all(threads == 1 for _, threads in found), found

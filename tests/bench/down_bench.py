"""How long `make down` takes with everything up (issue 38: at most 3 s), and that it leaves nothing.

Each cycle: `make up`, wait until `rmmdet health` says the loop is OK (or `--settle-s` passed), then time
`make down` and look for any process left from this checkout's virtualenv.

    python -m tests.bench.down_bench [--cycles 5] [--settle-s 60] [--readme]

Writes tests/bench/results/down.json; `--readme` the table in docs/live-system.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import time
from typing import Any

import numpy as np

from shared.machine import git_commit, machine_info
from shared.paths import REPO_ROOT

RESULTS = REPO_ROOT / "tests" / "bench" / "results"
RMMDET = REPO_ROOT / ".venv" / "bin" / "rmmdet"


def leftovers() -> list[str]:
    """Processes still running from this checkout's virtualenv."""
    out = subprocess.run(["ps", "-eo", "pid=,args="], capture_output=True, text=True, check=True).stdout
    prefix = str(REPO_ROOT / ".venv" / "bin")
    return [line.strip() for line in out.splitlines() if prefix in line and "down_bench" not in line]


def cycle(settle_s: float) -> dict[str, Any]:
    load_before = os.getloadavg()[0]  # other work on the machine (1 min load average)
    subprocess.run(["make", "up"], cwd=REPO_ROOT, check=True, capture_output=True)
    t0 = time.monotonic()
    healthy_s = None
    while time.monotonic() - t0 < settle_s:
        if subprocess.run([str(RMMDET), "health"], cwd=REPO_ROOT, capture_output=True).returncode == 0:
            healthy_s = time.monotonic() - t0
            break
        time.sleep(2.0)
    start = time.monotonic()
    subprocess.run(["make", "down"], cwd=REPO_ROOT, check=True, capture_output=True)
    down_s = time.monotonic() - start
    return {"load_before": load_before, "healthy_after_s": healthy_s, "down_s": down_s, "left": leftovers()}


def readme_table(record: dict[str, Any]) -> str:
    down = [c["down_s"] for c in record["cycles"]]
    left = sum(len(c["left"]) for c in record["cycles"])
    load = [c["load_before"] for c in record["cycles"]]
    healthy = sum(c["healthy_after_s"] is not None for c in record["cycles"])
    return (
        f"`make down` with everything `make up` starts, {len(down)} cycles (loop OK before the stop in "
        f"{healthy} of them): {min(down):.2f} / {float(np.median(down)):.2f} / {max(down):.2f} s (min / "
        f"median / max); processes left behind: {left}. Load average before the cycles' start "
        f"{min(load):.1f}-{max(load):.1f} "
        f"(other work on the machine). Commit {record['commit']}, {record['machine'].get('cpu_model', '?')}."
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--cycles", type=int, default=5)
    parser.add_argument("--settle-s", type=float, default=60.0, help="longest wait for a healthy loop")
    parser.add_argument("--readme", action="store_true", help="rewrite the table in docs/live-system.md")
    args = parser.parse_args()
    record = {
        "commit": git_commit(),
        "machine": machine_info(),
        "cycles": [cycle(args.settle_s) for _ in range(args.cycles)],
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "down.json").write_text(json.dumps(record, indent=2) + "\n")
    text = readme_table(record)
    print(text)
    if args.readme:
        from shared.readme import replace_section

        replace_section("down-bench", text, commit=record["commit"])


if __name__ == "__main__":
    main()

"""The live city bench (issue 53 item 3): `make up WORLD=city SHARDS=N` on a public real-city scenario with
its demand scaled up step by step, each for `--minutes` after `--warmup-s`: the world's real-time factor,
the running vehicles, request -> plan p50 / p95 (the city world's report lines, services/city), the
shards' handovers per minute (their health counters), `rmmdet health` at every probe. The largest fleet
is the highest scale whose every report line kept real time (RTF >= `--min-rtf` of the target).

    python -m tests.bench.city_live_bench [--scales 1 2 4 8] [--shards 4] [--minutes 3] [--readme]

Writes tests/bench/results/city_live.json (one entry per run, with the machine and the commit).
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import time
from typing import Any

import numpy as np

from shared.machine import git_commit, machine_info
from shared.paths import REPO_ROOT, RUN_DIR

RESULTS = REPO_ROOT / "tests" / "bench" / "results"
SECTION = "city-live-bench"
DEFAULT_SCENARIO = "tests/fixtures/real/sumo_scenarios/bologna_pasubio/run.sumocfg"
_REPORT = re.compile(
    r"t (\d+) s: RTF ([\d.]+), (\d+) running, (\d+) kept, (\d+) asking; request->plan p50 ([\d.na]+) / p95 "
    r"([\d.na]+) ms"
)


def make(*args: str, timeout_s: float = 600.0) -> None:
    subprocess.run(["make", *args], cwd=REPO_ROOT, check=True, timeout=timeout_s, capture_output=True)


def health_ok() -> bool:
    done = subprocess.run(
        [str(REPO_ROOT / ".venv" / "bin" / "rmmdet"), "health"], cwd=REPO_ROOT, capture_output=True, text=True
    )
    return "loop OK" in done.stdout


def shard_handovers(shards: int) -> int:
    """Vehicles adopted by every shard so far (their health counters)."""
    import zenoh

    from shared.bus.streams import shard_instance
    from shared.bus.zenoh_config import DEFAULT_CLIENT_CONFIG, zenoh_config
    from tests.integration.coordinator_client import coordinator_health, counters

    with zenoh.open(zenoh_config(DEFAULT_CLIENT_CONFIG)) as session:
        total = 0
        for region in range(shards):
            report = coordinator_health(session, instance=shard_instance(region) if shards > 1 else "cloud")
            total += counters(report).get("handovers/adopted", 0) if report is not None else 0
        return total


def run_one(scenario: str, scale: float, shards: int, warmup_s: float, minutes: float) -> dict[str, Any]:
    make("down")
    log = RUN_DIR / "logs" / "city.log"
    log.unlink(missing_ok=True)
    make("up", "WORLD=city", f"SCENARIO={scenario}", f"SHARDS={shards}", f"CITY_SCALE={scale:g}")
    try:
        time.sleep(warmup_s)
        start = len(log.read_text().splitlines()) if log.exists() else 0
        handovers0, t0 = shard_handovers(shards), time.monotonic()
        probes = []
        while time.monotonic() - t0 < minutes * 60:
            probes.append(health_ok())
            time.sleep(10)
        handovers = shard_handovers(shards) - handovers0
        elapsed_min = (time.monotonic() - t0) / 60
    finally:
        make("down")
    lines = log.read_text().splitlines()[start:] if log.exists() else []
    reports = [m.groups() for line in lines if (m := _REPORT.search(line))]
    rtf = [float(r[1]) for r in reports]
    running = [int(r[2]) for r in reports]
    p95 = [float(r[6]) for r in reports if r[6] != "nan"]
    return {
        "scale": scale,
        "shards": shards,
        "reports": len(reports),
        "rtf_min": min(rtf, default=float("nan")),
        "rtf_mean": float(np.mean(rtf)) if rtf else float("nan"),
        "running_max": max(running, default=0),
        "running_mean": float(np.mean(running)) if running else 0.0,
        "request_plan_p95_ms_max": max(p95, default=float("nan")),
        "request_plan_p95_ms_median": float(np.median(p95)) if p95 else float("nan"),
        "handovers_per_min": handovers / elapsed_min if elapsed_min > 0 else 0.0,
        "health_ok": sum(probes),
        "health_probes": len(probes),
    }


def readme_table(record: dict[str, Any]) -> str:
    lines = [
        f"`make up WORLD=city SHARDS={record['shards']}` on {record['scenario']}, demand scaled; "
        f"{record['minutes']:g} min measured after {record['warmup_s']:g} s per scale; commit "
        f"{record['commit']}, {record['machine'].get('cpu_model', '?')} "
        f"({record['machine'].get('cpu_count')} cores). Largest fleet in real time (every report's RTF >= "
        f"{record['min_rtf']}): "
        f"{record['largest_running']} running vehicles.",
        "",
        "| scale | running (mean / max) | RTF (min / mean) | request -> plan p95 ms (median / worst) | "
        "handovers per min | health OK |",
        "|---|---|---|---|---|---|",
    ]
    for r in record["runs"]:
        lines.append(
            f"| {r['scale']:g} | {r['running_mean']:.0f} / {r['running_max']} | {r['rtf_min']:.2f} / "
            f"{r['rtf_mean']:.2f} | {r['request_plan_p95_ms_median']:.0f} / "
            f"{r['request_plan_p95_ms_max']:.0f} | "
            f"{r['handovers_per_min']:.0f} | {r['health_ok']}/{r['health_probes']} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scenario", default=DEFAULT_SCENARIO)
    parser.add_argument("--scales", type=float, nargs="+", default=[1.0, 2.0, 4.0, 8.0])
    parser.add_argument("--shards", type=int, default=4)
    parser.add_argument("--warmup-s", type=float, default=120.0)
    parser.add_argument("--minutes", type=float, default=3.0)
    parser.add_argument("--min-rtf", type=float, default=0.95, help="real time: every report's RTF at least")
    parser.add_argument("--readme", action="store_true", help="rewrite the docs' city-live-bench table")
    args = parser.parse_args()
    runs = []
    for scale in args.scales:
        runs.append(run_one(args.scenario, scale, args.shards, args.warmup_s, args.minutes))
        print(json.dumps(runs[-1]), flush=True)
    held = [r for r in runs if r["reports"] and r["rtf_min"] >= args.min_rtf]
    record = {
        "scenario": args.scenario,
        "shards": args.shards,
        "warmup_s": args.warmup_s,
        "minutes": args.minutes,
        "min_rtf": args.min_rtf,
        "largest_running": max((r["running_max"] for r in held), default=0),
        "runs": runs,
        "commit": git_commit(),
        "machine": machine_info(),
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "city_live.json").write_text(json.dumps(record, indent=2, default=float) + "\n")
    text = readme_table(record)
    print(text)
    if args.readme:
        from shared.readme import replace_section

        replace_section(SECTION, text)


if __name__ == "__main__":
    main()

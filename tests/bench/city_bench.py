"""City-scale benchmark (issue 37): the coordinator's shards on a SUMO grid, lock step (studies/city).

A `--side` x `--side` grid of junctions `--edge-m` apart, every crossing with a roadside agent, demand
of each of `--vehicles` over the first half of `--duration`; for each (vehicles, shards) the rmmdet arm
runs once (seed 1). Reported per run: each shard's work per simulated step (its map updates and plans,
what its own process would do) p50 / p95 ms, the coordinator's CPU seconds per simulated second (all
shards) and per running vehicle, the whole process's (SUMO and the perception stand-in included), and
the trips. The coordinator is the district's (deploy/experiments/city.yaml `coordinator`), as the
scheduling study runs it. At the largest shard count: the cost per running vehicle from the smallest to
the largest fleet, the cost of one more running vehicle between successive fleets (flat when the cost
grows linearly), and the cores the coordinator would need for 50,000 vehicles on the fitted line.

    python -m tests.bench.city_bench [--side 10] [--vehicles 1000 3000 5000] [--shards 1 4 16] [--readme]

Writes tests/bench/results/city.json.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import sumolib

from shared.config import with_overrides
from shared.machine import git_commit, machine_info
from shared.paths import REPO_ROOT
from shared.traffic.config import load_coordinator_settings
from sim.sumo import demand, network
from sim.sumo.scene import coverage_layout
from studies.city.config import load_city_settings
from studies.city.run import CityRun, run_arm
from studies.experiments.oracle import OracleErrorModel

log = logging.getLogger("city_bench")
RESULTS = Path(__file__).resolve().parent / "results"
ORACLE_MODEL = REPO_ROOT / "deploy" / "experiments" / "oracle_model.json"
PROJECTED_VEHICLES = 50_000
SEED = 1


def bench(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    net = network.grid_network(
        network.GridSpec(junctions_per_side=args.side, edge_length_m=args.edge_m), work / "grid.net.xml"
    )
    layout = coverage_layout(sumolib.net.readNet(str(net)), 1.0, SEED, args.range_m)
    model = OracleErrorModel.load(ORACLE_MODEL)
    # The district's coordinator, as the scheduling study runs it (deploy/experiments/city.yaml).
    coordinator = with_overrides(load_coordinator_settings(), load_city_settings().coordinator)
    runs = []
    for vehicles in args.vehicles:
        spec = demand.DemandSpec(vehicles=vehicles, end_s=args.duration / 2, min_distance_m=2 * args.edge_m)
        routes = demand.routed_demand(net, spec, SEED, work / f"v{vehicles}.rou.xml")
        for shards in args.shards:
            t0 = time.perf_counter()
            run = CityRun(net, routes, layout, SEED, args.duration, shards=shards, max_vehicles=vehicles)
            result = run_arm(run, "rmmdet", coordinator, model, work / f"v{vehicles}_s{shards}")
            shard_ms = result["shard_ms"]
            busy_s = sum(s["busy_s"] for s in shard_ms.values())
            running = result["running_mean"]
            row = {
                "vehicles": vehicles,
                "shards": shards,
                "sim_s": result["sim_s"],
                "running_mean": running,
                "shard_p50_ms_max": max(s["p50_ms"] for s in shard_ms.values()),
                "shard_p95_ms_max": max(s["p95_ms"] for s in shard_ms.values()),
                "coordinator_cpu_s_per_sim_s": busy_s / result["sim_s"],
                "coordinator_cpu_s_per_sim_s_per_vehicle": busy_s / result["sim_s"] / max(running, 1e-9),
                "process_cpu_s_per_sim_s": result["cpu_s_per_sim_s"],
                "trips": result["trips"],
                "handovers": result["counts"].get("shards/handovers", 0),
                "max_owners": result["counts"].get("shards/max_owners", 0),
                "wall_s": time.perf_counter() - t0,
            }
            log.info("%s", row)
            runs.append(row)
    return {"runs": runs, "projection": projection(runs, max(args.shards))}


def projection(runs: list[dict[str, Any]], shards: int) -> dict[str, Any]:
    """At `shards`, the per-vehicle cost's change between the smallest and largest fleet, and the cores
    for PROJECTED_VEHICLES from the straight line through the coordinator's CPU per running vehicle."""
    rows = sorted((r for r in runs if r["shards"] == shards), key=lambda r: r["vehicles"])
    if len(rows) < 2:
        return {}
    x = np.array([r["running_mean"] for r in rows])
    y = np.array([r["coordinator_cpu_s_per_sim_s"] for r in rows])
    slope, intercept = np.polyfit(x, y, 1)
    per_vehicle = [r["coordinator_cpu_s_per_sim_s_per_vehicle"] for r in rows]
    # What one more running vehicle costs between successive fleets (the fixed per-shard work cancels):
    # linear scaling keeps it flat.
    marginal = [
        (b["coordinator_cpu_s_per_sim_s"] - a["coordinator_cpu_s_per_sim_s"])
        / (b["running_mean"] - a["running_mean"])
        for a, b in itertools.pairwise(rows)
    ]
    # Running vehicles scale with the fleet (same network, same demand window).
    running = PROJECTED_VEHICLES * rows[-1]["running_mean"] / rows[-1]["vehicles"]
    return {
        "shards": shards,
        "per_vehicle_change": per_vehicle[-1] / per_vehicle[0] - 1.0,
        "marginal_cpu_s_per_sim_s_per_vehicle": marginal,
        "marginal_change": marginal[-1] / marginal[0] - 1.0 if len(marginal) > 1 else None,
        "slope_cpu_s_per_sim_s_per_vehicle": float(slope),
        "intercept_cpu_s_per_sim_s": float(intercept),
        "vehicles": PROJECTED_VEHICLES,
        "running_vehicles": running,
        "cores": float(slope * running + intercept),
    }


def readme_table(record: dict[str, Any]) -> str:
    lines = [
        f"{record['grid']} grid, every crossing with an agent; commit {record['commit']}, "
        f"{record['machine'].get('cpu_model', '?')}; lock step, one process (`tests/bench/city_bench.py`).",
        "",
        "| vehicles | shards | running (mean) | shard work per step p50 / p95 ms (worst shard) | "
        "coordinator CPU s per sim s | per running vehicle, ms | handovers | mean travel time s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in record["runs"]:
        lines.append(
            f"| {r['vehicles']} | {r['shards']} | {r['running_mean']:.0f} | {r['shard_p50_ms_max']:.1f} / "
            f"{r['shard_p95_ms_max']:.1f} | {r['coordinator_cpu_s_per_sim_s']:.3f} | "
            f"{r['coordinator_cpu_s_per_sim_s_per_vehicle'] * 1e3:.3f} | {r['handovers']} | "
            f"{r['trips']['travel_time_mean_s']:.0f} |"
        )
    p = record.get("projection")
    if p:
        lines += [
            "",
            f"At {p['shards']} shards the coordinator's cost per running vehicle changed by "
            f"{p['per_vehicle_change'] * 100:+.0f} % between the smallest and the largest fleet (the "
            "per-shard work that does not grow with the fleet weighs most on the smallest); the cost of "
            "one more running vehicle between successive fleets was "
            + " / ".join(f"{m * 1e3:.3f}" for m in p["marginal_cpu_s_per_sim_s_per_vehicle"])
            + " ms per sim s"
            + (f" ({p['marginal_change'] * 100:+.0f} %)" if p.get("marginal_change") is not None else "")
            + f". On the fitted line, {p['vehicles']:,} vehicles ({p['running_vehicles']:.0f} running) need "
            f"{p['cores']:.1f} cores.",
        ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--side", type=int, default=10, help="junctions per side of the grid")
    parser.add_argument("--edge-m", type=float, default=200.0, help="junction spacing, m")
    parser.add_argument("--range-m", type=float, default=60.0, help="roadside agents' range, m")
    parser.add_argument("--vehicles", type=int, nargs="+", default=[1000, 3000, 5000])
    parser.add_argument("--shards", type=int, nargs="+", default=[1, 4, 16])
    parser.add_argument("--duration", type=float, default=600.0, help="simulated seconds per run")
    parser.add_argument("--work", type=Path, default=Path("/tmp/rmmdet_city_bench"))
    parser.add_argument("--readme", action="store_true", help="rewrite the README's city-bench table")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    args.work.mkdir(parents=True, exist_ok=True)
    record = {
        "grid": f"{args.side} x {args.side} ({args.edge_m:g} m)",
        "duration_s": args.duration,
        "commit": git_commit(),
        "machine": machine_info(),
        **bench(args, args.work),
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "city.json").write_text(json.dumps(record, indent=2, default=float) + "\n")
    text = readme_table(record)
    print(text)
    if args.readme:
        from shared.readme import replace_section

        replace_section("city-bench", text, commit=record["commit"])


if __name__ == "__main__":
    main()

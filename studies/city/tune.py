"""One run of the city study on a tuning seed, for choosing the district's coordinator settings.

    .venv/bin/python -m studies.city.tune --seed 101 --level near_capacity --arm rmmdet --coverage 1 \
        --coordinator '{"planner": {"detour_min_saving": 0.2}}'

The network, demand level, roadside range and duration are the study's (deploy/experiments/city.yaml);
`--coordinator` is merged over the study's own `coordinator` overrides. Prints one JSON line: the
settings run and the trips summary. Tuning seeds only (the study's seeds are held out: scored once per
change by `rmmdet experiments city`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import sumolib

from shared.config import with_overrides
from shared.traffic.config import load_coordinator_settings
from sim.sumo import demand, network
from sim.sumo.scene import coverage_layout
from studies.city.config import load_city_settings
from studies.city.run import ARMS, CityRun, run_arm
from studies.experiments.config import DEFAULT_ORACLE_MODEL
from studies.experiments.oracle import OracleErrorModel


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seed", type=int, required=True, help="a tuning seed (not one of the study's)")
    parser.add_argument("--level", required=True, help="demand level of the study (e.g. near_capacity)")
    parser.add_argument("--arm", choices=ARMS, default="rmmdet")
    parser.add_argument("--coverage", type=float, default=1.0, help="share of crossings with an agent")
    parser.add_argument("--coordinator", type=json.loads, default={}, help="JSON overrides of the settings")
    parser.add_argument("--work", type=Path, default=Path("/tmp/rmmdet_city_tune"))
    args = parser.parse_args()
    s = load_city_settings()
    if args.seed in s.seeds:
        parser.error(f"seed {args.seed} is one of the study's held-out seeds {s.seeds}")
    if args.level not in s.demand:
        parser.error(f"unknown level {args.level!r}: one of {sorted(s.demand)}")
    work = args.work / f"{args.level}_s{args.seed}"
    work.mkdir(parents=True, exist_ok=True)
    net = network.grid_network(network.GridSpec(s.grid_side, s.edge_length_m), work / "grid.net.xml")
    spec = demand.DemandSpec(
        vehicles=s.demand[args.level], end_s=s.departures_s, min_distance_m=2 * s.edge_length_m
    )
    routes = demand.routed_demand(net, spec, args.seed, work / "routes.rou.xml")
    layout = coverage_layout(sumolib.net.readNet(str(net)), args.coverage, args.seed, s.range_m)
    coordinator = with_overrides(with_overrides(load_coordinator_settings(), s.coordinator), args.coordinator)
    run = CityRun(net, routes, layout, args.seed, s.duration_s, reroute_period_s=s.reroute_period_s)
    result = run_arm(run, args.arm, coordinator, OracleErrorModel.load(DEFAULT_ORACLE_MODEL), work / args.arm)
    print(json.dumps({
        "seed": args.seed, "level": args.level, "arm": args.arm, "coverage": args.coverage,
        "planner": coordinator.planner.model_dump(mode="json"), "trips": result["trips"],
    }))  # fmt: skip


if __name__ == "__main__":
    main()

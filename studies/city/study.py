"""`rmmdet experiments city`: scheduling at scale on a SUMO grid or scenario, the coordinator against
SUMO's routing.

On a generated grid, the demand levels are routed demands (sim/sumo/demand.py); on a scenario
(`scenario:`, a .sumocfg, e.g. a public real city), its own files as SUMO reads them, each scaled by
`scale` (sim/sumo/scenario.py: copied into each run's folder, so its detector outputs land there). For
each demand level and seed, the demand is driven by every arm
(studies/city/run.py); arms that read the roadside agents (`sumo_covered`, `rmmdet`) run once per
coverage (a share of the crossings, drawn per seed). Compared per (demand, coverage): the coordinator's
mean travel time (departure delay included) and trips per hour against each baseline arm, as paired
differences over the seeds with 95 % t-intervals (`studies.stats`). Results: `<out>/results.json` and
the README's `city` table.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import sumolib

from shared.config import with_overrides
from shared.machine import git_commit, machine_info
from shared.traffic.config import load_coordinator_settings
from sim.sumo import demand, network
from sim.sumo.scenario import ScenarioError, load_scenario, preflight, stage
from sim.sumo.scene import RoadsideLayout, coverage_layout
from sim.sumo.world import KeptVehicles
from studies.city.config import CityStudySettings
from studies.city.run import CityRun, run_arm
from studies.experiments.config import DEFAULT_ORACLE_MODEL
from studies.experiments.oracle import OracleErrorModel
from studies.parallel import run_jobs
from studies.stats import paired_cell, paired_differences

log = logging.getLogger(__name__)

#: Arms whose routes do not depend on the roadside agents: run once per (demand, seed).
COVERAGE_FREE = ("as_given", "shortest", "sumo_oracle")
#: Figures compared between arms, per seed: (label, key of the trips summary, format of a difference).
COMPARED = (
    ("mean travel time s", "travel_time_mean_s", "{:+.1f}"),
    ("mean time loss s", "time_loss_mean_s", "{:+.1f}"),
    ("trips per hour", "trips_per_hour", "{:+.0f}"),
)


@dataclass(frozen=True)
class Job:
    settings_json: str
    net: Path  # the generated grid's (a scenario's come from its configuration, staged per run)
    routes: Path | None
    junctions: tuple[str, ...]
    level: str
    coverage: float | None
    seed: int
    arm: str
    out: Path
    scale: float = 1.0


def _run(job: Job) -> dict[str, Any]:
    s = CityStudySettings.model_validate_json(job.settings_json)
    layout = RoadsideLayout(job.junctions, s.range_m)
    keep = KeptVehicles(frozenset(s.routed_classes))
    if s.scenario is not None:
        scn = stage(load_scenario(s.scenario), job.out / "inputs")
        duration_s = s.duration_s if scn.end_s is None else scn.end_s - (scn.begin_s or 0.0)
        run = CityRun(
            scn.net, scn.routes, layout, job.seed, duration_s, reroute_period_s=s.reroute_period_s,
            shards=s.shards, additional=scn.additional, begin_s=scn.begin_s, scale=job.scale, keep=keep,
        )  # fmt: skip
    else:
        assert job.routes is not None
        run = CityRun(
            job.net, job.routes, layout, job.seed, s.duration_s, reroute_period_s=s.reroute_period_s,
            shards=s.shards, keep=keep,
        )  # fmt: skip
    model = OracleErrorModel.load(DEFAULT_ORACLE_MODEL)
    coordinator = with_overrides(load_coordinator_settings(), s.coordinator)
    result = run_arm(run, job.arm, coordinator, model, job.out)
    log.info("%s %s cov %s seed %d: %.1f s mean, %d trips", job.arm, job.level, job.coverage, job.seed,
             result["trips"]["travel_time_mean_s"], result["trips"]["trips"])  # fmt: skip
    return {"level": job.level, "coverage": job.coverage, **result}


def jobs(s: CityStudySettings, work: Path) -> list[Job]:
    """Every (demand level, seed, arm[, coverage]) run, the grid and its demands written under `work` (a
    scenario is read, and checked by SUMO once, here)."""
    if s.scenario is not None:
        # SUMO reads a copy once here (one clear error now, not one per run; what it writes stays there).
        source = load_scenario(s.scenario)
        scn = stage(source, work / "scenario")
        try:
            preflight(scn.net, scn.routes, scn.additional)
        except ScenarioError as err:  # named by the files the user gave, not their copies
            raise ScenarioError(
                str(err).replace(f"{work / 'scenario'}/", f"{source.config.parent}/")
            ) from None
        net_path = scn.net
        routes_of: dict[tuple[str, int], Path | None] = {
            (lv, seed): None for lv in s.levels() for seed in s.seeds
        }
        scale_of = dict(zip(s.levels(), s.scale, strict=True))
    else:
        net_path = network.grid_network(network.GridSpec(s.grid_side, s.edge_length_m), work / "grid.net.xml")
        routes_of = {}
        for level, vehicles in s.demand.items():
            spec = demand.DemandSpec(
                vehicles=vehicles, end_s=s.departures_s, min_distance_m=2 * s.edge_length_m
            )
            for seed in s.seeds:
                routes_of[(level, seed)] = demand.routed_demand(
                    net_path, spec, seed, work / level / f"s{seed}.rou.xml"
                )
        scale_of = {}
    net = sumolib.net.readNet(str(net_path))
    out = []
    for (level, seed), routes in routes_of.items():
        for arm in s.arms:
            for coverage in [None] if arm in COVERAGE_FREE else s.coverage:
                layout = coverage_layout(net, coverage if coverage is not None else 0.0, seed, s.range_m)
                folder = work / level / f"s{seed}" / (arm if coverage is None else f"{arm}_c{coverage:g}")
                out.append(
                    Job(
                        s.model_dump_json(),
                        net_path,
                        routes,
                        layout.junctions,
                        level,
                        coverage,
                        seed,
                        arm,
                        folder,
                        scale_of.get(level, 1.0),
                    )
                )
    return out


def comparisons(runs: list[dict[str, Any]], s: CityStudySettings) -> dict[str, Any]:
    """Per (demand, coverage) and baseline: the coordinator minus the baseline, paired by seed."""
    by = {(r["level"], r["arm"], r["coverage"], r["seed"]): r["trips"] for r in runs}
    out: dict[str, Any] = {}
    for level in s.levels():
        for coverage in s.coverage:
            row: dict[str, Any] = {}
            for base in s.baseline_arms:
                base_cov = None if base in COVERAGE_FREE else coverage
                pairs = [
                    (by[(level, base, base_cov, seed)], by[(level, "rmmdet", coverage, seed)])
                    for seed in s.seeds
                    if (level, base, base_cov, seed) in by and (level, "rmmdet", coverage, seed) in by
                ]
                row[base] = {
                    key: paired_differences([b[key] for b, _ in pairs], [a[key] for _, a in pairs])
                    for _, key, _ in COMPARED
                }
            out[f"{level}@{coverage:g}"] = row
    return out


def run_study(s: CityStudySettings, work: Path, out: Path) -> dict[str, Any]:
    t0 = time.perf_counter()
    ran_on: list[dict[str, Any]] = []
    runs = list(run_jobs(_run, jobs(s, work), s.workers, ran_on))
    body = {"settings": s.model_dump(mode="json"), "runs": runs, "comparisons": comparisons(runs, s)}
    return write_results(out, {**body, "ran_on": ran_on}, t0)


def write_results(out: Path, body: dict[str, Any], t0: float) -> dict[str, Any]:
    """`body` with the wall time since `t0` (perf_counter), the commit and the machine, written to
    `out/results.json`; the results."""
    results = {
        **body,
        "wall_s": round(time.perf_counter() - t0, 1),
        "commit": git_commit(),
        "machine": machine_info(),
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=2, default=float) + "\n")
    return results


def markdown_table(results: dict[str, Any]) -> str:
    """The README's city table: per demand level and coverage, the coordinator against each baseline."""
    s = results["settings"]
    where = (
        f"SUMO scenario {Path(s['scenario']).parent.name}/{Path(s['scenario']).name}"
        if s.get("scenario")
        else f"{s['grid_side']} x {s['grid_side']} SUMO grid ({s['edge_length_m']:g} m)"
    )
    head = (
        f"{where}, seeds {s['seeds']}, "
        f"{s['shards']} coordinator shard(s); rmmdet minus baseline per seed, mean ± 95 % CI (bold: the "
        f"interval excludes 0); coordinator overrides {s.get('coordinator') or 'none'}; commit "
        f"{results['commit']}, {results['machine'].get('cpu_model', '?')}."
    )
    bases = s["baseline_arms"]
    cols = [f"{label} vs {b}" for b in bases for label, _, _ in COMPARED]
    lines = [head, "", "| demand @ coverage | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
    for key, row in results["comparisons"].items():
        cells = [paired_cell(row[b][k], fmt) for b in bases for _, k, fmt in COMPARED]
        lines.append(f"| {key} | " + " | ".join(cells) + " |")
    arms = s["arms"]
    lines += ["", "Mean travel time, s (departure delay included), mean over the seeds:", "",
              "| demand @ coverage | " + " | ".join(arms) + " |", "|---|" + "---|" * len(arms)]  # fmt: skip
    for level in CityStudySettings.model_validate(s).levels():
        for coverage in s["coverage"]:
            cells = []
            for arm in arms:
                cov = None if arm in COVERAGE_FREE else coverage
                times = [r["trips"]["travel_time_mean_s"] for r in results["runs"]
                         if (r["level"], r["arm"], r["coverage"]) == (level, arm, cov)]  # fmt: skip
                cells.append(f"{sum(times) / len(times):.1f}" if times else "-")
            lines.append(f"| {level}@{coverage:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)

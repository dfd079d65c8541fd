"""`rmmdet experiments flow` as a study: the policy x fleet x seed grid, its aggregate and acceptance,
the full-perception run, heat maps, the summary and the results file. The CLI only parses and prints."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

from shared.config import with_overrides
from shared.machine import git_commit, machine_info
from shared.perception.config import MecSettings
from shared.scene.scene import Scene
from shared.traffic.config import CoordinatorSettings, load_coordinator_settings
from sim.config import SimSettings, load_sim_settings
from studies.experiments import report
from studies.experiments.config import FlowExperimentSettings
from studies.experiments.flow import RunResult, run_full_perception
from studies.experiments.oracle import ErrorObserver, OracleErrorModel
from studies.parallel import run_jobs

log = logging.getLogger(__name__)
#: Real-chain against oracle: the metrics whose paired interval must include zero for "agrees".
AGREEMENT = ("trips_per_hour", "matched_travel_time_s", "travel_time_mean_s")
RealJob = tuple[int, int, float, str, str, str, str]


def _real_chain_worker(job: RealJob) -> tuple[RunResult, ErrorObserver]:
    vehicles, seed, duration_s, exp_json, sim_json, coord_json, mec_json = job
    exp = FlowExperimentSettings.model_validate_json(exp_json)
    sim = SimSettings.model_validate_json(sim_json)
    coordinator = CoordinatorSettings.model_validate_json(coord_json)
    mec = MecSettings.model_validate_json(mec_json)
    scene = Scene.load(sim.scene)
    fit = exp.oracle_fit
    maps = coordinator.maps
    observer = ErrorObserver(
        scene, maps.dedup_gate_m, maps.level_separation_m, fit.distance_bin_m, fit.max_distance_m
    )
    result = run_full_perception(scene, sim, coordinator, exp, mec, vehicles, seed, duration_s, observer)
    return result, observer


def run_real_chain(
    exp: FlowExperimentSettings,
    sim: SimSettings,
    coordinator: CoordinatorSettings,
    mec: MecSettings,
    runs: list[tuple[int, int, float]],
) -> tuple[list[RunResult], ErrorObserver | None]:
    """(vehicles, seed, duration) closed-loop runs through the MEC chain, `exp.workers` in parallel
    (one onnxruntime thread per model each: the workers share the cores); their results and the
    pooled error measurements."""
    mec = with_overrides(mec, {"detectors": {"camera_threads": 1, "lidar_threads": 1}})
    # Only what was set: a dumped default would come back explicit and no longer scale with the scene.
    dumps = (
        exp.model_dump_json(exclude_unset=True),
        sim.model_dump_json(exclude_unset=True),
        coordinator.model_dump_json(exclude_unset=True),
        mec.model_dump_json(exclude_unset=True),
    )
    jobs: list[RealJob] = sorted(((n, s, d, *dumps) for n, s, d in runs), key=lambda j: -j[0])
    results: list[RunResult] = []
    pooled: ErrorObserver | None = None
    t0 = time.perf_counter()
    for result, observer in run_jobs(_real_chain_worker, jobs, exp.workers):
        results.append(result)
        if pooled is None:
            pooled = observer
        else:
            pooled.merge(observer)
        log.info(
            "real chain %d vehicles seed %d: %d trips (%d/%d, %.0f s)",
            result.vehicles,
            result.seed,
            len(result.trips),
            len(results),
            len(jobs),
            time.perf_counter() - t0,
        )
    return results, pooled


def fit_oracle(
    exp: FlowExperimentSettings, sim: SimSettings, coordinator: CoordinatorSettings, mec: MecSettings
) -> OracleErrorModel:
    """Fit the oracle's error model on real-chain runs of `exp.oracle_fit` and write it to
    `exp.oracle_model`."""
    fit = exp.oracle_fit
    runs = [(n, s, fit.duration_s) for n in fit.vehicle_counts for s in fit.seeds]
    _, observer = run_real_chain(exp, sim, coordinator, mec, runs)
    assert observer is not None
    model = observer.fit(
        {
            "seeds": fit.seeds,
            "vehicle_counts": fit.vehicle_counts,
            "duration_s": fit.duration_s,
            "policy": exp.full_perception.policy,
            "commit": git_commit(),
        }
    )
    model.save(exp.oracle_model)
    return model


def compare_real_chain(grid: list[RunResult], real: list[RunResult], policy: str) -> dict[str, Any]:
    """Real chain minus the oracle's run of `policy`, paired by (fleet, seed), and whether they agree:
    every `AGREEMENT` interval includes zero."""
    keys = {(r.vehicles, r.seed) for r in real}
    oracle = [r for r in grid if r.policy == policy and (r.vehicles, r.seed) in keys]
    paired = report.paired_differences(real + oracle, baseline=policy)
    agree = {}
    for n, row in paired.items():
        for arm, d in row.items():
            agree[f"{arm}_{n}_vehicles_agrees_with_oracle"] = all(
                d[m]["n"] > 1 and abs(d[m]["mean"]) <= d[m]["ci95"] for m in AGREEMENT
            )
    return {
        "aggregate": report.aggregate(real),
        "oracle_aggregate": report.aggregate(oracle),
        "paired": paired,
        "agreement": agree,
    }


def run_flow_study(exp: FlowExperimentSettings, mec: MecSettings, out: Path) -> tuple[dict[str, Any], str]:
    """Run the experiment, write `out/results.json`, `out/summary.md` and heat maps; the results and
    the summary (markdown)."""
    sim = load_sim_settings(exp.sim_config)
    coordinator = load_coordinator_settings(exp.coordinator_config)
    scene = Scene.load(sim.scene)
    t0 = time.perf_counter()
    fitted = fit_oracle(exp, sim, coordinator, mec) if exp.oracle_fit.enabled else None
    ran_on: list[dict[str, Any]] = []
    runs = report.run_grid(exp, sim, coordinator, ran_on)
    agg = report.aggregate(runs)
    results: dict[str, Any] = {
        "settings": json.loads(exp.model_dump_json()),
        "planner": json.loads(coordinator.planner.model_dump_json()),
        "aggregate": agg,
        "acceptance": report.acceptance(agg),
        "paired_vs_baseline": report.paired_differences(runs),
        "oracle_model": OracleErrorModel.load(exp.oracle_model).model_dump(),
        "oracle_fitted_now": fitted is not None,
        "runs": [r.summary() for r in runs],
        "ran_on": ran_on,
        "commit": git_commit(),
        "machine": machine_info(),
    }
    full = exp.full_perception
    if full.enabled:
        plan = [(n, s, full.duration_s) for n in full.vehicle_counts for s in full.seeds]
        real, observer = run_real_chain(exp, sim, coordinator, mec, plan)
        comparison = compare_real_chain(runs, real, full.policy)
        if observer is not None:
            comparison["measured_errors"] = observer.fit().model_dump()  # on these runs, for reference
        comparison["runs"] = [r.summary() for r in real]
        results["full_perception"] = comparison
        results["acceptance"].update(comparison["agreement"])
    results["wall_s"] = round(time.perf_counter() - t0, 1)
    out.mkdir(parents=True, exist_ok=True)
    results["heat_maps"] = report.write_heat_maps(runs, scene, exp.heat_map_cell_m, out)
    numbers = sorted(j.number for j in scene.spec.junctions)
    summary = report.markdown(agg, numbers, results.get("full_perception"))
    (out / "summary.md").write_text(summary)
    (out / "results.json").write_text(json.dumps(results, indent=2, default=float) + "\n")
    return results, summary

"""`rmmdet experiments flow` as a study: the policy x fleet x seed grid, its aggregate and acceptance,
the full-perception run, heat maps, the summary and the results file. The CLI only parses and prints."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from shared.machine import git_commit, machine_info
from shared.perception.config import MecSettings
from shared.scene.scene import Scene
from shared.traffic.config import load_coordinator_settings
from sim.config import load_sim_settings
from studies.experiments import report
from studies.experiments.config import FlowExperimentSettings
from studies.experiments.flow import run_full_perception


def run_flow_study(exp: FlowExperimentSettings, mec: MecSettings, out: Path) -> tuple[dict[str, Any], str]:
    """Run the experiment, write `out/results.json`, `out/summary.md` and heat maps; the results and
    the summary (markdown)."""
    sim = load_sim_settings(exp.sim_config)
    coordinator = load_coordinator_settings(exp.coordinator_config)
    scene = Scene.load(sim.scene)
    t0 = time.perf_counter()
    runs = report.run_grid(exp, sim, coordinator)
    agg = report.aggregate(runs)
    results: dict[str, Any] = {
        "settings": json.loads(exp.model_dump_json()),
        "planner": json.loads(coordinator.planner.model_dump_json()),
        "aggregate": agg,
        "acceptance": report.acceptance(agg),
        "paired_vs_baseline": report.paired_differences(runs),
        "runs": [r.summary() for r in runs],
        "commit": git_commit(),
        "machine": machine_info(),
    }
    full_summary = None
    if exp.full_perception.enabled:
        full_summary = run_full_perception(scene, sim, coordinator, exp, mec).summary()
        results["full_perception"] = full_summary
    results["wall_s"] = round(time.perf_counter() - t0, 1)
    out.mkdir(parents=True, exist_ok=True)
    results["heat_maps"] = report.write_heat_maps(runs, scene, exp.heat_map_cell_m, out)
    numbers = sorted(j.number for j in scene.spec.junctions)
    summary = report.markdown(agg, numbers, full_summary)
    (out / "summary.md").write_text(summary)
    (out / "results.json").write_text(json.dumps(results, indent=2, default=float) + "\n")
    return results, summary

"""Run the flow experiment grid and write its results: JSON, a Markdown summary with the paper's Table II
layout, and mean-speed heat maps.

Statistics per (fleet size, policy) over seeds: mean and a 95 % confidence interval of the mean
(Student t, n - 1 degrees of freedom). "Scheduled" is the `balanced` policy.
"""

from __future__ import annotations

import logging
import re
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from shared.scene.scene import Scene
from shared.traffic.config import CoordinatorSettings, PolicyName
from sim.config import SimSettings
from studies.experiments.config import FlowExperimentSettings
from studies.experiments.flow import RunResult, run_flow
from studies.parallel import run_jobs
from studies.stats import mean_ci, paired_cell

log = logging.getLogger(__name__)

SCHEDULED: PolicyName = "balanced"
METRICS = (
    "trips_per_hour",
    "travel_time_mean_s",
    "travel_time_p95_s",
    "delay_mean_s",
    "distance_m",
    "mean_speed_mps",
    "total_flow",
)
#: Every policy is compared with this one, paired by seed (same trips: per-vehicle trip draws).
BASELINE: PolicyName = "shortest"
#: Paired differences of a policy minus the baseline, per seed; "matched_travel_time_s" is over the
#: trips both runs completed (same vehicle, same k-th trip).
PAIRED = ("trips_per_hour", "matched_travel_time_s", "travel_time_mean_s", "delay_mean_s", "distance_m")
_FORMAT = {
    "total_flow": "{:.0f}",
    "trips_per_hour": "{:.0f}",
    "distance_m": "{:.0f}",
    "mean_speed_mps": "{:.3f}",
}  # others: "{:.1f}"


def _mean_ci_cells(row: dict[str, Any]) -> list[str]:
    """The cells `mean ± ci95` of every metric of one (fleet, policy) row, in `METRICS` order."""
    cells = []
    for m in METRICS:
        f = _FORMAT.get(m, "{:.1f}")
        cells.append(f"{f.format(row[m]['mean'])} ± {f.format(row[m]['ci95'])}")
    return cells


def _worker(job: tuple[str, int, int, str, str, str]) -> RunResult:
    policy, vehicles, seed, exp_json, sim_json, coord_json = job
    exp = FlowExperimentSettings.model_validate_json(exp_json)
    sim = SimSettings.model_validate_json(sim_json)
    coordinator = CoordinatorSettings.model_validate_json(coord_json)
    scene = Scene.load(sim.scene)
    return run_flow(scene, sim, coordinator, exp, policy, vehicles, seed)


def run_grid(
    exp: FlowExperimentSettings,
    sim: SimSettings,
    coordinator: CoordinatorSettings,
    placements: list[dict[str, Any]] | None = None,
) -> list[RunResult]:
    """Every (policy, fleet size, seed) run; processes in parallel (spawned, one per run, or on a Dask
    cluster: studies/parallel.py); where each ran into `placements` when given."""
    # Only what was set: a dumped default would come back explicit and no longer scale with the scene
    # (as the real-chain runs' workers get theirs, run.py).
    dumps = (
        exp.model_dump_json(exclude_unset=True),
        sim.model_dump_json(exclude_unset=True),
        coordinator.model_dump_json(exclude_unset=True),
    )
    # Longest first, so the pool does not end on one big run.
    jobs = sorted(
        ((p, n, s, *dumps) for n in exp.vehicle_counts for p in exp.policies for s in exp.seeds),
        key=lambda j: -j[1],
    )
    results: list[RunResult] = []
    t0 = time.perf_counter()
    # A progress bar on a terminal (tqdm disables itself when stderr is not one: logs stay clean).
    for r in tqdm(
        run_jobs(_worker, jobs, exp.workers, placements),
        total=len(jobs),
        desc="flow runs",
        unit="run",
        disable=None,
    ):
        results.append(r)
        log.info(
            "%s %d vehicles seed %d: flow %d, %d trips (%d/%d, %.0f s)",
            r.policy,
            r.vehicles,
            r.seed,
            r.total_flow,
            len(r.trip_times_s),
            len(results),
            len(jobs),
            time.perf_counter() - t0,
        )
    return results


def aggregate(results: list[RunResult]) -> dict[str, dict[str, Any]]:
    """{"<vehicles>": {"<policy>": {metric: mean/ci, "flow_per_junction": {...}}}}."""
    out: dict[str, dict[str, Any]] = {}
    groups: dict[tuple[int, str], list[RunResult]] = {}
    for r in results:
        groups.setdefault((r.vehicles, r.policy), []).append(r)
    for (n, policy), runs in sorted(groups.items()):
        summaries = [r.summary() for r in runs]
        row: dict[str, Any] = {m: mean_ci([s[m] for s in summaries]) for m in METRICS}
        junctions = sorted(runs[0].arrivals)
        row["flow_per_junction"] = {str(j): mean_ci([r.arrivals[j] for r in runs])["mean"] for j in junctions}
        if "lane_count_relative_error" in summaries[0]:
            row["lane_count_relative_error"] = mean_ci([s["lane_count_relative_error"] for s in summaries])
        row["seeds"] = sorted(r.seed for r in runs)
        out.setdefault(str(n), {})[policy] = row
    return out


def paired_differences(results: list[RunResult], baseline: str = BASELINE) -> dict[str, dict[str, Any]]:
    """{"<vehicles>": {"<policy>": {metric: mean/ci of (policy - baseline) over seeds}}}: each seed's
    run of the policy against the baseline's run on the same seed (same trips)."""
    runs = {(r.vehicles, r.policy, r.seed): r for r in results}
    diffs: dict[tuple[int, str], dict[str, list[float]]] = {
        key: {m: [] for m in PAIRED}
        for key in sorted({(r.vehicles, r.policy) for r in results})
        if key[1] != baseline
    }
    for (n, policy, seed), run in sorted(runs.items()):
        base = runs.get((n, baseline, seed))
        if policy == baseline or base is None:
            continue
        a, b = run.summary(), base.summary()
        for m in PAIRED:
            if m in a and a[m] is not None and b[m] is not None:
                diffs[n, policy][m].append(a[m] - b[m])
        matched = _matched_travel_time_difference(run, base)
        if matched is not None:
            diffs[n, policy]["matched_travel_time_s"].append(matched)
    out: dict[str, dict[str, Any]] = {}
    for (n, policy), d in diffs.items():
        out.setdefault(str(n), {})[policy] = {m: mean_ci(v) for m, v in d.items()}
    return out


def _matched_travel_time_difference(run: RunResult, base: RunResult) -> float | None:
    """Mean travel-time difference over the trips both runs completed (same vehicle, same k-th trip)."""
    mine = {(v, k): t for v, k, t, _ in run.trips}
    theirs = {(v, k): t for v, k, t, _ in base.trips}
    common = mine.keys() & theirs.keys()
    return float(np.mean([mine[c] - theirs[c] for c in common])) if common else None


def acceptance(agg: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The issue's checks: flow gain at the smallest fleet; travel times at the larger ones."""
    checks: dict[str, Any] = {}
    sizes = sorted(int(n) for n in agg)
    if not sizes:
        return checks
    small = agg[str(sizes[0])]
    if SCHEDULED in small and "random" in small:
        gain = small[SCHEDULED]["total_flow"]["mean"] / small["random"]["total_flow"]["mean"] - 1.0
        checks[f"flow_gain_vs_random_{sizes[0]}_vehicles"] = gain
    for n in sizes[1:]:
        row = agg[str(n)]
        if SCHEDULED not in row:
            continue
        tt = row[SCHEDULED]["travel_time_mean_s"]["mean"]
        for base in ("shortest", "dynamic_ground_truth"):
            if base in row:
                checks[f"travel_time_{n}_vehicles_{SCHEDULED}_minus_{base}_s"] = (
                    tt - row[base]["travel_time_mean_s"]["mean"]
                )
    return checks


def markdown(agg: dict[str, dict[str, Any]], junction_numbers: list[int], full: dict[str, Any] | None) -> str:
    lines = ["# Flow experiment", ""]
    for n, row in agg.items():
        lines += [f"## {n} vehicles", ""]
        lines.append("| policy | " + " | ".join(METRICS) + " |")
        lines.append("|---|" + "---|" * len(METRICS))
        for policy, r in row.items():
            lines.append(f"| {policy} | " + " | ".join(_mean_ci_cells(r)) + " |")
        lines += ["", "Flow per junction (mean over seeds; the paper's Table II):", ""]
        lines.append("| policy | " + " | ".join(str(j) for j in junction_numbers) + " | total |")
        lines.append("|---|" + "---|" * (len(junction_numbers) + 1))
        for policy, r in row.items():
            per = [r["flow_per_junction"][str(j)] for j in junction_numbers]
            lines.append(f"| {policy} | " + " | ".join(f"{v:.0f}" for v in per) + f" | {sum(per):.0f} |")
        lines.append("")
    if full:
        lines += ["## Real chain against the oracle", "", *real_chain_lines(full), ""]
    return "\n".join(lines)


def write_heat_maps(results: list[RunResult], scene: Scene, cell_m: float, out_dir: Path) -> list[str]:
    """Mean speed per cell, pooled over seeds, one PNG per fleet size with a panel per policy."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    table = scene.spec.table
    extent = (
        table.origin_m[0],
        table.origin_m[0] + table.size_x_m,
        table.origin_m[1],
        table.origin_m[1] + table.size_y_m,
    )
    written = []
    for n in sorted({r.vehicles for r in results}):
        policies = list(dict.fromkeys(r.policy for r in results if r.vehicles == n))
        fig = Figure(figsize=(3.2 * len(policies), 4.2))
        FigureCanvasAgg(fig)
        for k, policy in enumerate(policies):
            runs = [r for r in results if r.vehicles == n and r.policy == policy]
            total = np.sum([r.speed_sum for r in runs], axis=0)
            count = np.sum([r.speed_samples for r in runs], axis=0)
            mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
            ax = fig.add_subplot(1, len(policies), k + 1)
            im = ax.imshow(mean, origin="lower", extent=extent, vmin=0.0, vmax=0.5, cmap="viridis")
            ax.set_title(f"{policy}", fontsize=9)
            ax.set_xticks([])
            ax.set_yticks([])
        fig.colorbar(im, ax=fig.axes, shrink=0.8, label="mean speed (m/s)")
        fig.suptitle(f"mean vehicle speed, {n} vehicles, {cell_m} m cells")
        path = out_dir / f"speed_heat_map_{n}_vehicles.png"
        fig.savefig(path, dpi=110)
        written.append(path.name)
    return written


def readme_section(results: dict[str, Any], junction_numbers: list[int]) -> str:
    """The README's flow tables and headline figures, from `results` (what `run_flow_study` wrote):
    every fleet and policy, the smallest fleet's flow per junction (random against scheduled), the
    checks of `acceptance` and the full-perception run."""
    agg, checks = results["aggregate"], results["acceptance"]
    settings = results["settings"]
    lines = [
        f"Seeds {settings['seeds']} × {settings['duration_s']:g} simulated s per run, "
        f"{results['wall_s']:g} s wall with {settings['workers']} workers; "
        f"commit {results.get('commit', '?')}.",
        "",
        "| Vehicles | Policy | Trips / h | Travel time mean (s) | Travel time p95 (s) | Delay over free "
        "flow (s) | Distance (m) | Mean speed (m/s) | Junction entries (the paper's flow) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    order = {p: i for i, p in enumerate(settings.get("policies", []))}  # as configured: baselines first
    for n, row in agg.items():
        for policy, r in sorted(row.items(), key=lambda kv: order.get(kv[0], len(order))):
            name = f"**`{policy}`**" if policy == SCHEDULED else f"`{policy}`"
            lines.append(f"| {n} | {name} | " + " | ".join(_mean_ci_cells(r)) + " |")
    paired = results.get("paired_vs_baseline", {})
    if paired:
        lines += [
            "",
            f"Each policy minus `{BASELINE}`, paired by seed (same trips), mean ± 95 % interval over the "
            "seeds; **bold**: the interval excludes zero. Matched travel time: over the trips both runs "
            "completed.",
            "",
            "| Vehicles | Policy | Δ trips / h | Δ matched travel time (s) | Δ travel time mean (s) "
            "| Δ delay (s) | Δ distance (m) |",
            "|---|---|---|---|---|---|---|",
        ]
        for n, row in paired.items():
            for policy, d in sorted(row.items(), key=lambda kv: order.get(kv[0], len(order))):
                cells = [
                    paired_cell(d[m], "{:+.0f}" if m in ("trips_per_hour", "distance_m") else "{:+.1f}")
                    for m in PAIRED
                ]
                lines.append(f"| {n} | `{policy}` | " + " | ".join(cells) + " |")
    small = min(agg, key=int)
    lines += [
        "",
        f"Per junction with {small} vehicles (the paper's Table II: 624 → 668, +7.1 %):",
        "",
        "| Policy | " + " | ".join(str(j) for j in junction_numbers) + " | Total |",
        "|---|" + "---|" * (len(junction_numbers) + 1),
    ]
    for policy, label in (("random", "random (before)"), (SCHEDULED, f"{SCHEDULED} (scheduled)")):
        if policy in agg[small]:
            per = [agg[small][policy]["flow_per_junction"][str(j)] for j in junction_numbers]
            lines.append(f"| {label} | " + " | ".join(f"{v:.0f}" for v in per) + f" | {sum(per):.0f} |")
    lines.append("")
    for key, value in checks.items():
        gain = re.fullmatch(r"flow_gain_vs_random_(\d+)_vehicles", key)
        tt = re.fullmatch(r"travel_time_(\d+)_vehicles_(\w+)_minus_(\w+)_s", key)
        if gain:
            pct = 100 * value
            lines.append(f"- {gain[1]} vehicles: `{SCHEDULED}` flow against random turns {pct:+.1f} %")
        elif tt:
            lines.append(f"- {tt[1]} vehicles: `{tt[2]}` mean travel time minus `{tt[3]}`'s: {value:+.1f} s")
    for n, row in agg.items():
        if SCHEDULED in row and "lane_count_relative_error" in row[SCHEDULED]:
            err = row[SCHEDULED]["lane_count_relative_error"]
            lines.append(
                f"- {n} vehicles: the oracle maps' lane counts off by {100 * err['mean']:.0f} % (balanced)"
            )
    if "oracle_model" in results:
        lines += ["", *oracle_model_lines(results["oracle_model"])]
    full = results.get("full_perception")
    if full:
        lines += ["", *real_chain_lines(full)]
    return "\n".join(lines)


def oracle_model_lines(model: dict[str, Any]) -> list[str]:
    """The oracle's fitted error model as a table: recall per distance bin and agent, and the rest."""
    fitted = model.get("fitted_on", {})
    bin_m = model["distance_bin_m"]
    agents = model["agents"]
    bins = max(len(a["recall_by_distance"]) for a in agents.values())
    used = [k for k in range(bins) if any(a["present_by_distance"][k] for a in agents.values())]
    lines = [
        f"The oracle's error model, fitted on real-chain runs (seeds {fitted.get('seeds')}, "
        f"{fitted.get('vehicle_counts')} vehicles, {fitted.get('duration_s')} s each, "
        f"`{fitted.get('policy')}`, commit {fitted.get('commit')}): position error "
        f"{1000 * model['position_std_m']:.1f} mm and velocity error "
        f"{1000 * model['velocity_std_mps']:.0f} mm/s RMS per axis over {model['matched']} matched objects; "
        f"object lists {1000 * model['latency_s']:.0f} ms old on average when a map update reads them.",
        "",
        "| Agent | "
        + " | ".join(f"{k * bin_m:g}-{(k + 1) * bin_m:g} m" for k in used)
        + " | false positives / list |",
        "|---|" + "---|" * (len(used) + 1),
    ]
    for agent, a in agents.items():
        cells = [f"{a['recall_by_distance'][k]:.2f}" if a["present_by_distance"][k] else "-" for k in used]
        lines.append(f"| {agent} | " + " | ".join(cells) + f" | {a['false_positives_per_list']:.2f} |")
    lines += ["", "(recall by horizontal distance from the agent's sensors; '-': no vehicle that far)"]
    return lines


def real_chain_lines(full: dict[str, Any]) -> list[str]:
    """Real chain against the oracle, paired by seed, and whether they agree (`run.AGREEMENT`)."""
    lines = [
        "Real chain (rendered sensors -> MEC cores -> coordinator core) against the oracle, same policy, "
        "seeds and trips; real minus oracle, mean ± 95 % interval over the seeds (**bold**: excludes zero):",
        "",
        "| Vehicles | Trips / h real | Trips / h oracle | Δ trips / h | Δ matched travel time (s) "
        "| Δ travel time mean (s) | Agree | Lane-count error real / oracle |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for n, row in full["paired"].items():
        for arm, d in row.items():
            real_row = full["aggregate"][n][arm]
            oracle_row = next(iter(full["oracle_aggregate"][n].values()))
            real, oracle = real_row["trips_per_hour"], oracle_row["trips_per_hour"]
            errors = "/".join(
                f"{100 * r['lane_count_relative_error']['mean']:.0f} %"
                if "lane_count_relative_error" in r
                else "-"
                for r in (real_row, oracle_row)
            )
            agree = full["agreement"].get(f"{arm}_{n}_vehicles_agrees_with_oracle")
            cells = [
                paired_cell(d[m], "{:+.0f}" if m == "trips_per_hour" else "{:+.1f}")
                for m in ("trips_per_hour", "matched_travel_time_s", "travel_time_mean_s")
            ]
            counts = [f"{x['mean']:.0f} ± {x['ci95']:.0f}" for x in (real, oracle)]
            lines.append(
                f"| {n} | " + " | ".join(counts + cells) + f" | {'yes' if agree else 'no'} | {errors} |"
            )
    return lines

"""`rmmdet eval wire`: what the devices' wire formats do to accuracy, on the production MEC core.

Four arms on the same seeds (the fusion evaluation's, `studies/evaluation/fusion.py`, one run per
(agent, seed)):

- `sim`: the scene's own sensors, messages straight from the simulator (the default `make up`);
- `devices`: the site's lidars fire their devices' rays (RS-LiDAR-16 / -32 angle tables, lens offset,
  firing grid: `SiteFile.simulated_scene`), messages straight from the simulator;
- `wire`: the `devices` captures through the wire and back, in-process (`WireRoundTrip`): each lidar
  scan encoded as the unit's MSOP packets and decoded by the adapter's LidarStream (5 mm ranges,
  intensity in 1/255 steps); each radar scan as the ARS 408's cluster list and assembled by its
  ListAssembler (0.2 m positions, 0.25 m/s velocities, 0.5 dBm^2 RCS, no elevation, no SNR); camera
  JPEGs unchanged (the adapter passes the stream's JPEGs through). Stamps stay the tick's: the
  live path's clocks and transport are tested in tests/integration/test_wire.py, not here
  (`studies/evaluation/wire_path.py`);
- `wire_radar_model`: `wire`, with the MEC's radar noise model (what its fusion and tracker expect)
  raised to the ARS 408's quantisation (`with_ars408_noise`): what recovers the radar agent.

`wire` against `devices` isolates the wire formats' resolution; `devices` against `sim` the real
devices' ray patterns. Per agent: tracked AP-BEV@0.7 (lidar agents: also the lidar detector's own),
the radar's targets (radar agent), and the paired difference over seeds with a 95 % t-interval.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from shared.machine import git_commit, machine_info
from shared.perception.config import MecSettings
from studies.dataset.config import DatasetSettings
from studies.evaluation import fusion as fe
from studies.evaluation import robustness

DEFAULT_SITE = "deploy/devices/sand_table_wire.yaml"
T_95 = 0.975


ARMS = (
    robustness.Perturbation("sim"),
    robustness.Perturbation("devices", site=DEFAULT_SITE),
    robustness.Perturbation("wire", site=DEFAULT_SITE, wire=True),
    # what would recover the radar: the MEC told the ARS 408's real noise (its quantisation)
    robustness.Perturbation("wire_radar_model", site=DEFAULT_SITE, wire=True, radar_noise="ars408"),
)


def _row(summary: dict[str, Any]) -> dict[str, Any]:
    out = {"tracked_ap": summary["tracked"]["ap_bev_0.7"]}
    for output in ("lidar", "radar"):
        if output in summary:
            out[f"{output}_ap"] = summary[output]["ap_bev_0.7"]
            out[f"{output}_pose_p95_m"] = summary[output]["pose_error_p95_m"]
            out[f"{output}_f1"] = summary[output].get("f1")
    return out


def paired(a: list[float | None], b: list[float | None]) -> dict[str, float]:
    """Mean of b - a over the seeds where both are defined (an AP is None where a seed has nothing to
    score), and its 95 % t-interval."""
    d = np.asarray([y - x for x, y in zip(a, b, strict=True) if x is not None and y is not None], float)
    if len(d) == 0:
        return {"mean": math.nan, "ci_low": math.nan, "ci_high": math.nan}
    mean = float(d.mean())
    if len(d) < 2:
        return {"mean": mean, "ci_low": math.nan, "ci_high": math.nan}
    half = float(stats.t.ppf(T_95, len(d) - 1) * d.std(ddof=1) / math.sqrt(len(d)))
    return {"mean": mean, "ci_low": mean - half, "ci_high": mean + half}


def run_wire_study(
    dataset: DatasetSettings,
    mec: MecSettings,
    agents: list[str],
    seeds: list[int],
    duration_s: float,
    warmup_s: float,
    workers: int,
    out: Path,
) -> dict[str, Any]:
    """Every arm on every seed, one evaluation per seed (for the paired differences)."""
    t0 = time.perf_counter()
    per_seed: dict[str, dict[int, dict[str, Any]]] = {arm.name: {} for arm in ARMS}
    pooled: dict[str, dict[str, Any]] = {}
    for arm in ARMS:
        evaluations: dict[str, fe.AgentEvaluation] = {}
        for seed in seeds:
            ev = fe.evaluate(agents, [seed], duration_s, warmup_s, mec, workers, dataset.variation, arm)
            per_seed[arm.name][seed] = {a: _row(fe.summarise(e)) for a, e in ev.items() if a != "all"}
            for name, e in ev.items():
                if name != "all":
                    evaluations.setdefault(name, fe.AgentEvaluation()).merge(e)
        pooled[arm.name] = {name: _row(fe.summarise(e)) for name, e in evaluations.items()}
        out.mkdir(parents=True, exist_ok=True)  # what is done so far survives a later failure
        (out / "partial.json").write_text(json.dumps({"per_seed": per_seed, "pooled": pooled}, default=float))
    differences: dict[str, dict[str, Any]] = {}
    for base, other in (("devices", "wire"), ("sim", "devices"), ("wire", "wire_radar_model")):
        for agent in agents:
            for key in pooled[other][agent]:
                if not key.endswith("_ap"):
                    continue
                before = [per_seed[base][s][agent].get(key) for s in seeds]
                after = [per_seed[other][s][agent].get(key) for s in seeds]
                pair = paired(before, after)
                differences.setdefault(f"{other} - {base}", {}).setdefault(agent, {})[key] = pair
    results = {
        "agents": agents,
        "seeds": seeds,
        "duration_s": duration_s,
        "warmup_s": warmup_s,
        "site": DEFAULT_SITE,
        "wall_s": round(time.perf_counter() - t0, 1),
        "commit": git_commit(),
        "machine": machine_info(),
        "pooled": pooled,
        "per_seed": per_seed,
        "differences": differences,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=2, default=float) + "\n")
    (out / "partial.json").unlink(missing_ok=True)  # superseded: only a failed run leaves it
    return results


def markdown_table(results: dict[str, Any]) -> str:
    head = (
        f"Seeds {results['seeds']} x {results['duration_s']:g} s after {results['warmup_s']:g} s, "
        f"{results['wall_s']:g} s wall; commit {results['commit']}, "
        f"{results['machine'].get('cpu_model', '?')}. AP-BEV@0.7 pooled over the seeds; the difference "
        "is paired over seeds, mean [95 % t-interval]."
    )
    lines = [
        head,
        "",
        "| agent | output | sim | devices | wire | wire, MEC told the ARS 408's noise | wire - devices "
        "| devices - sim | told - wire |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    pooled, diff = results["pooled"], results["differences"]
    for agent in results["agents"]:
        for key in pooled["wire"][agent]:
            if not key.endswith("_ap"):
                continue

            def ci(name: str, agent: str = agent, key: str = key) -> str:
                d = diff[name][agent][key]
                return f"{d['mean']:+.3f} [{d['ci_low']:+.3f}, {d['ci_high']:+.3f}]"

            def ap(arm: str, agent: str = agent, key: str = key) -> str:
                value = pooled[arm][agent].get(key)
                return "-" if value is None else f"{value:.3f}"

            lines.append(
                f"| {agent} | {key.removesuffix('_ap')} | {ap('sim')} | {ap('devices')} | {ap('wire')} | "
                f"{ap('wire_radar_model')} | "
                f"{ci('wire - devices')} | {ci('devices - sim')} | {ci('wire_radar_model - wire')} |"
            )
    return "\n".join(lines)

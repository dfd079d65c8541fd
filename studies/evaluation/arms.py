"""Arms of a study on the same seeds: each arm a `robustness.Perturbation` of the fusion evaluation's
run (studies/evaluation/fusion.py, the production MEC core), one evaluation per (arm, seed), and paired
differences between arms over the seeds with a 95 % t-interval. Used by `rmmdet eval wire` and
`rmmdet eval calibration`."""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from shared.machine import git_commit, machine_info
from shared.perception.config import MecSettings
from studies.dataset.config import DatasetSettings
from studies.evaluation import fusion as fe
from studies.evaluation import robustness
from studies.stats import paired_differences


def row(summary: dict[str, Any]) -> dict[str, Any]:
    out = {"tracked_ap": summary["tracked"]["ap_bev_0.7"]}
    for output in ("lidar", "radar"):
        if output in summary:
            out[f"{output}_ap"] = summary[output]["ap_bev_0.7"]
            out[f"{output}_pose_p95_m"] = summary[output]["pose_error_p95_m"]
            out[f"{output}_f1"] = summary[output].get("f1")
    return out


def paired(a: list[float | None], b: list[float | None]) -> dict[str, float]:
    """Mean of b - a over the seeds where both are defined (an AP is None where a seed has nothing to
    score), and its 95 % t-interval as bounds."""
    d = paired_differences(a, b)
    return {"mean": d["mean"], "ci_low": d["mean"] - d["ci95"], "ci_high": d["mean"] + d["ci95"]}


def run_arms(
    arms: Sequence[robustness.Perturbation],
    comparisons: Sequence[tuple[str, str]],
    dataset: DatasetSettings,
    mec: MecSettings,
    agents: list[str],
    seeds: list[int],
    duration_s: float,
    warmup_s: float,
    workers: int,
    out: Path,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Every arm on every seed, one evaluation per seed, and for each (base, other) of `comparisons`
    the paired difference other - base of each AP per agent; written to `out`/results.json with
    `extra` (what the arms were run on)."""
    t0 = time.perf_counter()
    per_seed: dict[str, dict[int, dict[str, Any]]] = {arm.name: {} for arm in arms}
    pooled: dict[str, dict[str, Any]] = {}
    for arm in arms:
        evaluations: dict[str, fe.AgentEvaluation] = {}
        for seed in seeds:
            ev = fe.evaluate(agents, [seed], duration_s, warmup_s, mec, workers, dataset.variation, arm)
            per_seed[arm.name][seed] = {a: row(fe.summarise(e)) for a, e in ev.items() if a != "all"}
            for name, e in ev.items():
                if name != "all":
                    evaluations.setdefault(name, fe.AgentEvaluation()).merge(e)
        pooled[arm.name] = {name: row(fe.summarise(e)) for name, e in evaluations.items()}
        out.mkdir(parents=True, exist_ok=True)  # what is done so far survives a later failure
        (out / "partial.json").write_text(json.dumps({"per_seed": per_seed, "pooled": pooled}, default=float))
    differences: dict[str, dict[str, Any]] = {}
    for base, other in comparisons:
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
        **(extra or {}),
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

"""`rmmdet eval fusion` as a study: every (agent, seed) run through the MEC core, summarised, with the
heat maps, the Kalman noise experiment and the results file. The CLI only parses and prints."""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from shared.config import load_settings, with_overrides
from shared.machine import git_commit, machine_info
from shared.paths import DEFAULT_SCENE, REPO_ROOT
from shared.perception.confidence import ScoreCalibration
from shared.perception.config import DEFAULT_MEC_CONFIG, MecSettings
from shared.scene.scene import Scene
from studies.dataset.conditions import SeedConditions
from studies.dataset.config import DEFAULT_DATASET_CONFIG, DatasetSettings
from studies.evaluation import fusion as fe
from studies.evaluation import kalman_noise, robustness


@dataclass(frozen=True)
class EvalSite:
    """What a fusion evaluation runs on: the scene file, the MEC settings (`mec_data`: the profile's
    composed settings, None for the MEC's own file), the sim settings' overrides, the seeds' file and
    the results' folder."""

    scene_path: Path
    mec_data: dict[str, Any] | None
    sim_overrides: dict[str, Any]
    dataset_file: Path
    results_base: Path

    def mec(self, config: Path | None = None, lidar: str | None = None) -> MecSettings:
        """The MEC settings: `config` if given, else the profile's (else the MEC's file); `lidar`
        replaces the lidar detector, the rest as configured."""
        if config is not None or self.mec_data is None:
            mec = load_settings(MecSettings, config or DEFAULT_MEC_CONFIG)
        else:
            mec = load_settings(MecSettings, None, **self.mec_data)
        return mec if lidar is None else with_overrides(mec, {"detectors": {"lidar": lidar}})


def eval_site(scene_name: str | None = None) -> EvalSite:
    """The sand table (None) or a profile scene (deploy/profiles/scene/<name>.yaml) as `make up
    SCENE=<name>` composes it (shared/supervision/profiles.py), its seeds in deploy/datasets/<name>.yaml
    and its results under docs/eval/<name>/."""
    if scene_name is None:
        return EvalSite(DEFAULT_SCENE, None, {}, DEFAULT_DATASET_CONFIG, Path("docs/eval"))
    from shared.supervision.profiles import scene_profile

    site = scene_profile(scene_name)
    # Lock-step runs have no coordinator: the vehicles route as the sim's own file says.
    sim_overrides = site.overrides.get("sim", {})
    sim_overrides = {**sim_overrides, "traffic": {**sim_overrides.get("traffic", {})}}
    sim_overrides["traffic"].pop("route_policy", None)
    return EvalSite(
        site.scene,
        site.settings["mec"],
        sim_overrides,
        REPO_ROOT / "deploy" / "datasets" / f"{scene_name}.yaml",
        Path("docs/eval") / scene_name,
    )


def run_fusion_study(
    scene: Scene,
    dataset: DatasetSettings,
    mec: MecSettings,
    agents: list[str],
    seeds: list[int],
    duration_s: float,
    warmup_s: float,
    workers: int,
    noise: bool,
    out: Path,
    split: str = "",
    scene_path: Path = DEFAULT_SCENE,
    sim_overrides: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Evaluate `seeds` (the fusion split `split`, "" for chosen seeds) under each seed's conditions,
    on `scene_path` with the sim settings' `sim_overrides`; summarise per agent and for all; write
    `out/results.json` and plots; the results."""
    t0 = time.perf_counter()
    per_seed: dict[str, dict[str, dict[str, float | None]]] = {}
    ran_on: list[dict[str, Any]] = []
    evaluations = fe.evaluate(
        agents,
        seeds,
        duration_s,
        warmup_s,
        mec,
        workers,
        dataset.variation,
        per_seed=per_seed,
        scene_path=scene_path,
        sim_overrides=sim_overrides,
        placements=ran_on,
    )
    results: dict[str, Any] = {
        "scene": scene.spec.scene_id,
        "static_track_speed_mps": fe.EvalDistances.for_scene(scene).static_track_speed_mps,
        "split": split,
        "agents": agents,
        "seeds": seeds,
        "conditions": [SeedConditions.draw(dataset.variation, s).as_dict() for s in seeds],
        "duration_s": duration_s,
        "warmup_s": warmup_s,
        "wall_s": round(time.perf_counter() - t0, 1),
        "commit": git_commit(),
        "machine": machine_info(),
    }
    for name, ev in evaluations.items():
        summary = fe.summarise(ev)
        summary["fusion_gain"] = fe.fusion_gain(summary)
        results[name] = summary
    results["per_seed"] = per_seed  # tracked AP / MOTA per (agent, seed): paired comparisons
    results["ran_on"] = ran_on
    out.mkdir(parents=True, exist_ok=True)
    results["heat_maps"] = fe.write_heat_maps(evaluations["all"], scene, out)
    if noise:
        runs = kalman_noise.run_noise(
            scene,
            seeds[0],
            SeedConditions.draw(dataset.variation, seeds[0]).vehicles,
            kalman_noise.PAPER_VARIANCES_M2,
            duration_s,
            warmup_s,
        )
        results["kalman_noise"] = [r.summary() for r in runs]
        kalman_noise.plot(runs, out / "kalman_noise.png")
    (out / "results.json").write_text(json.dumps(results, indent=2, default=float) + "\n")
    return results


def run_score_calibration(
    dataset: DatasetSettings,
    mec: MecSettings,
    agents: list[str],
    seeds: list[int],
    duration_s: float,
    warmup_s: float,
    workers: int,
    out: Path,
) -> tuple[ScoreCalibration, dict[str, Any]]:
    """Evaluate `seeds` (the tuning split) with raw scores, fit the calibrated-score curves and write
    them to `out`; the calibration and the raw scores' check (`fe.calibration_check`)."""
    raw = with_overrides(mec, {"score_calibration": None})
    evaluations = fe.evaluate(agents, seeds, duration_s, warmup_s, raw, workers, dataset.variation)
    calibration = fe.fit_calibration(evaluations["all"])
    calibration.save(
        out,
        fitted_on={"seeds": seeds, "agents": agents, "duration_s": duration_s, "warmup_s": warmup_s},
        commit=git_commit(),
    )
    return calibration, fe.calibration_check(evaluations["all"])


def run_robustness_study(
    dataset: DatasetSettings,
    mec: MecSettings,
    agents: list[str],
    seeds: list[int],
    duration_s: float,
    warmup_s: float,
    workers: int,
    out: Path,
    perturbations: tuple[robustness.Perturbation, ...] = robustness.PERTURBATIONS,
) -> dict[str, Any]:
    """The clean run and each of `perturbations` on the same seeds; the tracked output's accuracy per
    agent, and its share of the clean AP-BEV@0.7. Writes `out/results.json`."""
    t0 = time.perf_counter()
    runs: dict[str, Any] = {}
    for perturbation in (robustness.CLEAN, *perturbations):
        evaluations = fe.evaluate(
            agents, seeds, duration_s, warmup_s, mec, workers, dataset.variation, perturbation
        )
        runs[perturbation.name] = {
            "perturbation": dataclasses.asdict(perturbation),
            **{name: fe.summarise(ev)["tracked"] for name, ev in evaluations.items()},
        }
    for run in runs.values():
        for agent in [*agents, "all"]:
            clean_ap = runs["clean"][agent]["ap_bev_0.7"]
            run[agent]["ap_share_of_clean"] = run[agent]["ap_bev_0.7"] / clean_ap if clean_ap else None
        run["keeps_80_percent"] = all(
            (run[a]["ap_share_of_clean"] or 0.0) >= robustness.KEEP_SHARE for a in [*agents, "all"]
        )
    results = {
        "agents": agents,
        "seeds": seeds,
        "duration_s": duration_s,
        "warmup_s": warmup_s,
        "wall_s": round(time.perf_counter() - t0, 1),
        "commit": git_commit(),
        "machine": machine_info(),
        "runs": runs,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=2, default=float) + "\n")
    return results

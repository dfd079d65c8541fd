"""`rmmdet experiments cities`: the city study on public real-city SUMO scenarios (issue 53 item 2).

One scenario is for tuning: each candidate coordinator setting (`CANDIDATES`) drives the rmmdet arm on
its tuning seeds at every coverage, and the one with the lowest mean travel time is chosen. Every other
scenario is held out: it runs the whole study (every arm and coverage, the held-out seeds) once, with
the chosen setting. Results: `<out>/results.json` and the docs' `city-real` table (per held-out
scenario: the coordinator minus each baseline, paired over the seeds with 95 % CIs; each arm's means).
Settings: `deploy/experiments/city-real.yaml` (`RealCitiesSettings`).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

from pydantic import Field

from shared.config import RmmdetSettings, load_settings, settings_config
from shared.paths import REPO_ROOT
from studies.city.config import CityStudySettings, load_city_settings
from studies.city.study import COMPARED, COVERAGE_FREE, run_study, write_results
from studies.stats import paired_cell

log = logging.getLogger(__name__)

DEFAULT_REAL_CONFIG = REPO_ROOT / "deploy" / "experiments" / "city-real.yaml"
SECTION = "city-real"
#: The coordinator settings tuning chooses from: the table's as deployed, and the district's (chosen on
#: the generated grid's tuning seeds: deploy/experiments/city.yaml `coordinator`).
CANDIDATES = {
    "table": lambda: {},
    "district": lambda: load_city_settings().coordinator,
}


class RealCitiesSettings(RmmdetSettings):
    model_config = settings_config(env_prefix="RMMDET_CITIES_")

    scenarios: dict[str, Path] = Field(
        description="name -> SUMO configuration (.sumocfg; relative paths from the repository root)"
    )
    tuning: str = Field(description="the scenario settings are chosen on (not reported with the others)")
    tuning_seeds: list[int] = Field([101, 102], min_length=2, description="seeds of the tuning runs")
    candidates: list[str] = Field(list(CANDIDATES), min_length=1, description="coordinator settings tried")
    study: dict[str, Any] = Field(
        {}, description="the city study's settings for every scenario (seeds: the held-out seeds)"
    )

    def path(self, name: str) -> Path:
        path = self.scenarios[name]
        return path if path.is_absolute() else REPO_ROOT / path


def load_real_settings(path: Path | None = DEFAULT_REAL_CONFIG) -> RealCitiesSettings:
    s = load_settings(RealCitiesSettings, path)
    unknown = sorted(set(s.candidates) - set(CANDIDATES))
    if s.tuning not in s.scenarios or unknown:
        raise ValueError(
            f"tuning scenario {s.tuning!r} not among {sorted(s.scenarios)}, or unknown candidates {unknown}"
        )
    return s


def _study(s: RealCitiesSettings, name: str, **update: Any) -> CityStudySettings:
    return CityStudySettings.model_validate({**s.study, "scenario": s.path(name), **update})


def tune(s: RealCitiesSettings, work: Path, out: Path) -> dict[str, Any]:
    """Every candidate on the tuning scenario's tuning seeds (rmmdet arm, every coverage): mean travel time
    per candidate and the chosen one."""
    scores: dict[str, float] = {}
    for name in s.candidates:
        study = _study(s, s.tuning, seeds=s.tuning_seeds, arms=["rmmdet"], baseline_arms=[],
                       coordinator=CANDIDATES[name]())  # fmt: skip
        runs = run_study(study, work / "tuning" / name, out / "tuning" / name)["runs"]
        times = [r["trips"]["travel_time_mean_s"] for r in runs]
        scores[name] = sum(times) / len(times)
        log.info(
            "tuning %s on %s: %.1f s mean travel time over %d runs", name, s.tuning, scores[name], len(runs)
        )
    chosen = min(scores, key=scores.__getitem__)
    return {"scenario": s.tuning, "seeds": s.tuning_seeds, "mean_travel_time_s": scores, "chosen": chosen}


def run_cities(s: RealCitiesSettings, work: Path, out: Path) -> dict[str, Any]:
    t0 = time.perf_counter()
    tuning = tune(s, work, out)
    coordinator = CANDIDATES[tuning["chosen"]]()
    held_out = {}
    for name in s.scenarios:
        if name != s.tuning:
            held_out[name] = run_study(_study(s, name, coordinator=coordinator), work / name, out / name)
    return write_results(
        out, {"settings": s.model_dump(mode="json"), "tuning": tuning, "held_out": held_out}, t0
    )


def markdown_table(results: dict[str, Any]) -> str:
    """The docs' table: per held-out scenario, level and coverage, the coordinator minus each baseline;
    then each arm's means."""
    tuning = results["tuning"]
    scores = ", ".join(f"{k} {v:.1f} s" for k, v in tuning["mean_travel_time_s"].items())
    any_study = next(iter(results["held_out"].values()))["settings"]
    lines = [
        f"Tuned on {tuning['scenario']} (seeds {tuning['seeds']}; rmmdet mean travel time per candidate: "
        f"{scores}; chosen: **{tuning['chosen']}**); held out: {', '.join(results['held_out'])}, seeds "
        f"{any_study['seeds']}, each scored once. rmmdet minus baseline per seed, mean ± 95 % CI (bold: the "
        f"interval excludes 0; negative times are gains). Commit {results['commit']}, "
        f"{results['machine'].get('cpu_model', '?')}.",
        "",
    ]
    bases = any_study["baseline_arms"]
    cols = [f"{label} vs {b}" for b in bases for label, key, _ in COMPARED if key != "trips_per_hour"]
    lines += ["| scenario | level @ coverage | " + " | ".join(cols) + " |", "|---|---|" + "---|" * len(cols)]
    for name, study in results["held_out"].items():
        for key, row in study["comparisons"].items():
            cells = [
                paired_cell(row[b][k], fmt) for b in bases for _, k, fmt in COMPARED if k != "trips_per_hour"
            ]
            lines.append(f"| {name} | {key} | " + " | ".join(cells) + " |")
    lines += ["", "Each arm's means over the seeds: travel time s / time loss s / trips per hour / teleports "
              "(departure delay included in both times):", "",
              "| scenario | level @ coverage | " + " | ".join(any_study["arms"]) + " |",
              "|---|---|" + "---|" * len(any_study["arms"])]  # fmt: skip
    for name, study in results["held_out"].items():
        s = CityStudySettings.model_validate(study["settings"])
        for level in s.levels():
            for coverage in s.coverage:
                cells = []
                for arm in s.arms:
                    cov = None if arm in COVERAGE_FREE else coverage
                    runs = [
                        r for r in study["runs"] if (r["level"], r["arm"], r["coverage"]) == (level, arm, cov)
                    ]
                    cells.append(_means(runs))
                lines.append(f"| {name} | {level}@{coverage:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _means(runs: list[dict[str, Any]]) -> str:
    if not runs:
        return "-"
    n = len(runs)
    travel = sum(r["trips"]["travel_time_mean_s"] for r in runs) / n
    loss = sum(r["trips"]["time_loss_mean_s"] for r in runs) / n
    per_hour = sum(r["trips"]["trips_per_hour"] for r in runs) / n
    teleports = sum(r["counts"].get("teleports", 0) for r in runs) / n
    return f"{travel:.1f} / {loss:.1f} / {per_hour:.0f} / {teleports:.1f}"

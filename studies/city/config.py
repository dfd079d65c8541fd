"""City study settings (`deploy/experiments/city.yaml`; env `RMMDET_CITY_<FIELD>`, nested with `__`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import Field

from shared.config import RmmdetSettings, load_settings, settings_config
from shared.paths import REPO_ROOT
from sim.sumo.world import ROUTED_CLASSES
from studies.city.run import ARMS

DEFAULT_CITY_CONFIG = REPO_ROOT / "deploy" / "experiments" / "city.yaml"


class CityStudySettings(RmmdetSettings):
    model_config = settings_config(env_prefix="RMMDET_CITY_")

    scenario: Path | None = Field(
        None,
        description="a SUMO configuration (.sumocfg) run instead of the generated grid: its net, route and "
        "additional files, begin and end as SUMO reads them (then `scale` gives the demand levels)",
    )
    scale: list[float] = Field(
        [1.0],
        min_length=1,
        description="with a scenario: its demand scaled by SUMO (--scale), one level each",
    )
    routed_classes: list[str] = Field(
        list(ROUTED_CLASSES),
        description="vehicle classes the arms route; vehicles of other classes, on public transport lines or "
        "with stops keep their routes (counted `kept/<reason>`)",
    )
    grid_side: int = Field(10, ge=2, description="junctions per side of the netgenerate grid")
    edge_length_m: float = Field(200.0, gt=0, description="junction spacing, SUMO metres")
    demand: dict[str, int] = Field(
        {"free_flow": 1000, "near_capacity": 3000, "congested": 5000},
        description="demand levels: vehicles departing over the first `departures_s`",
    )
    departures_s: float = Field(600.0, gt=0, description="vehicles depart evenly over this, s")
    duration_s: float = Field(
        1800.0, gt=0, description="simulated seconds per run (or until all arrived; a scenario's end first)"
    )
    seeds: list[int] = Field([1, 2, 3, 4, 5], min_length=2, description="demand and layout seeds")
    coverage: list[float] = Field([1.0, 0.5, 0.25], description="shares of crossings with a roadside agent")
    range_m: float = Field(60.0, gt=0, description="a roadside agent's range, SUMO metres")
    arms: list[str] = Field(list(ARMS), description="arms compared (studies/city/run.py)")
    baseline_arms: list[str] = Field(
        ["as_given", "shortest", "sumo_oracle", "sumo_covered"],
        description="arms the coordinator is compared with",
    )
    reroute_period_s: float = Field(60.0, gt=0, description="SUMO arms reroute every vehicle this often")
    shards: int = Field(1, ge=1, description="coordinator shards of the rmmdet arm")
    coordinator: dict[str, Any] = Field(
        {},
        description="overrides of the coordinator settings for the district (nested like coordinator.yaml), "
        "chosen on tuning seeds",
    )
    workers: int = Field(2, ge=1, description="runs in parallel (processes: libsumo is one per process)")

    def levels(self) -> list[str]:
        """The demand levels: the scenario's scales (`x1`, `x1.5`), else the generated demands' names."""
        return [scale_level(k) for k in self.scale] if self.scenario is not None else list(self.demand)


def scale_level(scale: float) -> str:
    return f"x{scale:g}"


def load_city_settings(path: Path | None = DEFAULT_CITY_CONFIG) -> CityStudySettings:
    return load_settings(CityStudySettings, path)

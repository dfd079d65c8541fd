"""Flow experiment settings (`deploy/experiments/flow.yaml`; env `RMMDET_FLOW_<FIELD>`, nested with `__`)."""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, field_validator

from shared.config import RmmdetSettings, load_settings, settings_config
from shared.paths import REPO_ROOT
from shared.traffic.config import DEFAULT_COORDINATOR_CONFIG, POLICIES, PolicyName
from sim.config import DEFAULT_SIM_CONFIG

DEFAULT_FLOW_CONFIG = REPO_ROOT / "deploy" / "experiments" / "flow.yaml"
DEFAULT_ORACLE_MODEL = REPO_ROOT / "deploy" / "experiments" / "oracle_model.json"
#: Where each map-reading policy gets its maps unless its arm says (`paper_rule@ground_truth`).
DEFAULT_MAPS: dict[str, str] = {
    "paper_rule": "perceived",
    "balanced": "perceived",
    "dynamic_ground_truth": "ground_truth",
}
MAP_SOURCES = ("perceived", "ground_truth")


def parse_arm(arm: str) -> tuple[PolicyName, str | None]:
    """An experiment arm `<policy>[@<maps>]` as (policy, maps source or None for map-free policies).
    Raises ValueError on an unknown policy, an unknown source, or maps for a policy that reads none."""
    policy, _, maps = arm.partition("@")
    if policy not in POLICIES:
        raise ValueError(f"unknown policy {policy!r} in arm {arm!r} (policies: {', '.join(POLICIES)})")
    default = DEFAULT_MAPS.get(policy)
    if maps and default is None:
        raise ValueError(f"arm {arm!r}: {policy} reads no maps")
    if maps and maps not in MAP_SOURCES:
        raise ValueError(f"arm {arm!r}: maps must be one of {', '.join(MAP_SOURCES)}")
    return policy, (maps or default)


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class OracleFit(_Section):
    """Closed-loop runs with the real chain that the oracle's error model is fitted on (`oracle.py`);
    seeds apart from the experiment's."""

    enabled: bool = Field(True, description="fit before the grid (else read `oracle_model` as it is)")
    seeds: list[int] = Field([311, 312], min_length=1, description="scenario seeds of the fit")
    vehicle_counts: list[int] = Field([10, 20], min_length=1, description="fleet sizes of the fit")
    duration_s: float = Field(60.0, gt=0, description="simulated seconds per fit run")
    distance_bin_m: float = Field(0.5, gt=0, description="recall is measured per bin of distance")
    max_distance_m: float = Field(8.0, gt=0, description="the last bin ends here (recall 0 beyond)")


class FullPerceptionRuns(_Section):
    """Closed-loop runs with the real chain (rendered sensors -> MEC pipelines -> maps -> plans) on
    seeds and fleets of the grid, compared with the oracle's runs of the same policy, paired by seed."""

    enabled: bool = Field(True, description="run them (minutes each: every sensor is rendered)")
    vehicle_counts: list[int] = Field([10, 20], min_length=1, description="fleet sizes")
    seeds: list[int] = Field([301, 302, 303], min_length=1, description="scenario seeds (of the grid's)")
    duration_s: float = Field(300.0, gt=0, description="simulated seconds per run")
    policy: PolicyName = Field("balanced", description="policy planned on the perceived maps")


class FlowExperimentSettings(RmmdetSettings):
    model_config = settings_config(env_prefix="RMMDET_FLOW_")

    vehicle_counts: list[int] = Field([10, 20, 40], description="fleet sizes")
    seeds: list[int] = Field([301, 302, 303, 304, 305], min_length=2, description="scenario seeds")
    duration_s: float = Field(300.0, gt=0, description="simulated seconds per run")
    policies: list[str] = Field(
        list(POLICIES),
        description="arms compared: a route policy, or `<policy>@ground_truth` / `@perceived` to choose "
        "the maps a map-reading policy plans on",
    )
    map_period_s: float = Field(0.5, gt=0, description="perceived maps are updated this often")
    heat_map_cell_m: float = Field(0.125, gt=0, description="cell of the mean-speed heat maps (paper's)")
    speed_sample_period_s: float = Field(0.1, gt=0, description="vehicle speeds sampled this often")
    workers: int = Field(2, ge=1, description="runs in parallel (processes)")
    oracle_model: Path = Field(DEFAULT_ORACLE_MODEL, description="the oracle's fitted error model (JSON)")
    oracle_fit: OracleFit = OracleFit()
    full_perception: FullPerceptionRuns = FullPerceptionRuns()
    sim_config: Path = Field(DEFAULT_SIM_CONFIG, description="sim settings (vehicles, traffic model)")
    coordinator_config: Path = Field(DEFAULT_COORDINATOR_CONFIG, description="maps and planner settings")

    @field_validator("policies")
    @classmethod
    def _known_arms(cls, arms: list[str]) -> list[str]:
        for arm in arms:
            parse_arm(arm)
        return arms


def load_flow_settings(path: Path | None = DEFAULT_FLOW_CONFIG) -> FlowExperimentSettings:
    return load_settings(FlowExperimentSettings, path)

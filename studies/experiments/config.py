"""Flow experiment settings (`deploy/experiments/flow.yaml`; env `RMMDET_FLOW_<FIELD>`, nested with `__`)."""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

from shared.config import RmmdetSettings, load_settings, settings_config
from shared.paths import REPO_ROOT
from shared.traffic.config import DEFAULT_COORDINATOR_CONFIG, POLICIES, PolicyName
from sim.config import DEFAULT_SIM_CONFIG

DEFAULT_FLOW_CONFIG = REPO_ROOT / "deploy" / "experiments" / "flow.yaml"


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class OraclePerception(_Section):
    """Per-agent object lists from ground truth with an error model like the MECs' measured one."""

    position_std_m: float = Field(0.02, ge=0, description="per-axis position noise")
    velocity_std_mps: float = Field(0.03, ge=0, description="per-axis velocity noise")
    detection_probability: float = Field(
        0.95, ge=0, le=1, description="chance a vehicle in an agent's areas is reported in a map update"
    )


class FullPerceptionRun(_Section):
    """One closed-loop run with the real chain: rendered sensors -> MEC pipelines -> maps -> plans."""

    enabled: bool = Field(True, description="run it (minutes: every sensor is rendered)")
    vehicles: int = Field(10, ge=1, description="fleet size")
    seed: int = Field(301, ge=0, description="scenario seed")
    duration_s: float = Field(60.0, gt=0, description="simulated seconds")
    policy: PolicyName = Field("balanced", description="policy planned on the perceived maps")


class FlowExperimentSettings(RmmdetSettings):
    model_config = settings_config(env_prefix="RMMDET_FLOW_")

    vehicle_counts: list[int] = Field([10, 20, 40], description="fleet sizes")
    seeds: list[int] = Field([301, 302, 303, 304, 305], min_length=2, description="scenario seeds")
    duration_s: float = Field(300.0, gt=0, description="simulated seconds per run")
    policies: list[PolicyName] = Field(list(POLICIES), description="route policies compared")
    map_period_s: float = Field(0.5, gt=0, description="perceived maps are updated this often")
    heat_map_cell_m: float = Field(0.125, gt=0, description="cell of the mean-speed heat maps (paper's)")
    speed_sample_period_s: float = Field(0.1, gt=0, description="vehicle speeds sampled this often")
    workers: int = Field(2, ge=1, description="runs in parallel (processes)")
    oracle: OraclePerception = OraclePerception()
    full_perception: FullPerceptionRun = FullPerceptionRun()
    sim_config: Path = Field(DEFAULT_SIM_CONFIG, description="sim settings (vehicles, traffic model)")
    coordinator_config: Path = Field(DEFAULT_COORDINATOR_CONFIG, description="maps and planner settings")


def load_flow_settings(path: Path | None = DEFAULT_FLOW_CONFIG) -> FlowExperimentSettings:
    return load_settings(FlowExperimentSettings, path)

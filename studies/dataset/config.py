"""Dataset generation settings: which seeds go to which split, how long each seed runs, how often the
sensors are sampled, and how traffic, noise and appearance vary from seed to seed.

Loaded from a YAML file (deploy/datasets/*.yaml) with environment overrides `RMMDET_DATASET_<FIELD>`.
The number of frames is seeds x duration x rate: camera images = seeds x duration_s x
camera_sample_hz x 13 cameras; lidar frames = seeds x duration_s x lidar_sample_hz x 2 agents.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, model_validator

from shared.config import RmmdetSettings, settings_config
from shared.paths import REPO_ROOT
from sim.config import DEFAULT_SIM_CONFIG

DEFAULT_DATASET_CONFIG = REPO_ROOT / "deploy" / "datasets" / "default.yaml"
DEFAULT_DATA_ROOT = REPO_ROOT / "data" / "datasets"


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class SplitSeeds(_Model):
    train: list[int] = Field(default_factory=lambda: list(range(1, 25)), description="training seeds")
    val: list[int] = Field(default_factory=lambda: list(range(101, 104)), description="validation seeds")
    test: list[int] = Field(default_factory=lambda: list(range(201, 206)), description="held-out test seeds")
    fusion_tuning: list[int] = Field(
        default_factory=lambda: list(range(201, 206)),
        description="the fusion evaluation's tuning seeds: fusion and tracking settings were chosen on "
        "these (the detectors' test seeds: no detector was tuned on them)",
    )
    fusion_test: list[int] = Field(
        default_factory=lambda: list(range(501, 506)),
        description="the fusion evaluation's held-out seeds: nothing is chosen on them; scored once per "
        "change, never iterated on",
    )

    @model_validator(mode="after")
    def _disjoint(self) -> SplitSeeds:
        seen: set[int] = set()
        for split in (self.train, self.val, self.test, self.fusion_test):
            overlap = seen & set(split)
            if overlap or len(set(split)) != len(split):
                raise ValueError(f"seeds must be unique and splits disjoint; repeated: {sorted(overlap)}")
            seen |= set(split)
        if set(self.fusion_tuning) & set(self.train):
            raise ValueError("the fusion tuning seeds must not be detector training seeds")
        return self

    def items(self) -> list[tuple[str, int]]:
        return [(s, seed) for s in ("train", "val", "test") for seed in getattr(self, s)]


class Variation(_Model):
    """Per-seed choices (drawn from a generator seeded by the scenario seed)."""

    vehicles: list[int] = Field([6, 10, 16, 24], description="traffic densities to choose from")
    camera_noise_std: list[float] = Field([0.0, 0.01, 0.02], description="pixel noise (fraction of 255)")
    lidar_range_noise_std_m: list[float] = Field([0.003, 0.006, 0.01], description="lidar range noise")
    random_vehicle_colours: bool = Field(True, description="random body colour per vehicle (else palette)")
    light_ambient: tuple[float, float] = Field((0.35, 0.75), description="ambient coefficient range")
    light_diffuse: tuple[float, float] = Field((0.3, 0.7), description="diffuse coefficient range")
    light_elevation_deg: tuple[float, float] = Field((25.0, 85.0), description="light elevation range")


class DatasetSettings(RmmdetSettings):
    model_config = settings_config(env_prefix="RMMDET_DATASET_")

    sim_settings: Path = Field(
        DEFAULT_SIM_CONFIG, description="base sim settings (scene, tick rate, traffic)"
    )
    sim_overrides: dict[str, Any] = Field(
        default_factory=dict,
        description="deep-merged over `sim_settings` (a profile scene's: its scene file and sim overrides, "
        "as `rmmdet dataset generate --scene NAME` fills them in)",
    )
    seeds: SplitSeeds = SplitSeeds()
    warmup_s: float = Field(5.0, ge=0, description="simulated seconds before sampling (traffic spreads out)")
    duration_s: float = Field(60.0, gt=0, description="simulated seconds sampled per seed")
    camera_sample_hz: float = Field(
        1.0, ge=0, description="images per camera per simulated second (0 = none)"
    )
    lidar_sample_hz: float = Field(
        1.0, ge=0, description="lidar frames per agent per simulated second (0 = none)"
    )
    variation: Variation = Variation()

"""A seed's conditions: traffic density, sensor noise, lighting and vehicle colours, all drawn from the seed.

The one home of what varies from seed to seed (`config.Variation` gives the ranges). The dataset
generator and the fusion evaluation both run a seed under `SeedConditions.draw(variation, seed)`:
the same seed gives the same conditions in both, so the fusion evaluation scores the detectors under
the conditions their test split had, not on clean sensors.

    conditions = SeedConditions.draw(Variation(), 501)
    with conditions.lockstep(scene, sim_settings, sensor_ids=...) as sim:   # noise + lighting + colours
        ...
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from shared.scene.scene import Scene
from sim.config import SimSettings
from sim.lockstep import LockstepSim
from sim.sensors.camera import Lighting
from sim.traffic import TrafficSim
from studies.dataset.config import Variation

#: Separates the appearance generator from the traffic's (both are seeded by the scenario seed).
APPEARANCE_STREAM = 0x4150
#: Body colour channels are drawn in this range (no pure black or white cars).
COLOUR_MIN, COLOUR_MAX = 0.05, 0.95
#: The radar model's measurement noise (`radar_noise_scale` scales them together).
RADAR_NOISE_FIELDS = ("range_noise_std_m", "azimuth_noise_std_rad", "range_rate_noise_std_mps")


@dataclass(frozen=True)
class SeedConditions:
    """What one seed runs under. Noise: camera pixel noise std as a fraction of 255, lidar range noise
    std in metres; lighting: TinyRenderer's; `colour_seed` None keeps the scene's palette colours."""

    seed: int
    vehicles: int
    camera_noise_std: float
    lidar_range_noise_std_m: float
    lighting: Lighting
    colour_seed: int | None
    radar_noise_scale: float = 1.0  # the scene's radar noise times this (robustness studies)

    @classmethod
    def draw(cls, variation: Variation, seed: int) -> SeedConditions:
        """The seed's conditions (reproducible from the seed; independent of the traffic's draws)."""
        rng = np.random.default_rng([seed, APPEARANCE_STREAM])
        azimuth = rng.uniform(0, 2 * math.pi)
        elevation = math.radians(rng.uniform(*variation.light_elevation_deg))
        vehicles = int(rng.choice(variation.vehicles))
        camera_noise = float(rng.choice(variation.camera_noise_std))
        lidar_noise = float(rng.choice(variation.lidar_range_noise_std_m))
        direction = (
            math.cos(elevation) * math.cos(azimuth),
            math.cos(elevation) * math.sin(azimuth),
            math.sin(elevation),
        )
        ambient = float(rng.uniform(*variation.light_ambient))
        diffuse = float(rng.uniform(*variation.light_diffuse))
        colour_seed = int(rng.integers(2**31))
        return cls(
            seed=seed,
            vehicles=vehicles,
            camera_noise_std=camera_noise,
            lidar_range_noise_std_m=lidar_noise,
            lighting=Lighting(direction=direction, ambient=ambient, diffuse=diffuse),
            colour_seed=colour_seed if variation.random_vehicle_colours else None,
        )

    def model_overrides(self, scene: Scene) -> dict[str, dict[str, Any]]:
        """Sensor model fields per kind (`LockstepSim(model_overrides=...)`)."""
        out: dict[str, dict[str, Any]] = {
            "camera": {"image_noise_std": self.camera_noise_std},
            "lidar": {"range_noise_std_m": self.lidar_range_noise_std_m},
        }
        if self.radar_noise_scale != 1.0:
            models = {s.radar for s in scene.sensors_of(kind="radar") if s.radar is not None}
            if len(models) != 1:
                raise ValueError("scaling radar noise needs one radar model shared by the scene's radars")
            (model,) = models
            out["radar"] = {
                name: getattr(model, name) * self.radar_noise_scale for name in RADAR_NOISE_FIELDS
            }
        return out

    def paint(self, traffic: TrafficSim) -> None:
        """Give every vehicle its body colour for this seed (no-op with palette colours)."""
        if self.colour_seed is None:
            return
        colours = np.random.default_rng(self.colour_seed).uniform(
            COLOUR_MIN, COLOUR_MAX, (len(traffic.vehicles), 3)
        )
        for vehicle, rgb in zip(traffic.vehicles, colours, strict=True):
            vehicle.rgba = (float(rgb[0]), float(rgb[1]), float(rgb[2]), 1.0)

    def lockstep(self, scene: Scene, sim_settings: SimSettings, **kwargs: Any) -> LockstepSim:
        """A lock-step sim of `sim_settings` under these conditions (`kwargs` go to LockstepSim)."""
        sim = LockstepSim(
            scene, sim_settings, model_overrides=self.model_overrides(scene), lighting=self.lighting, **kwargs
        )
        self.paint(sim.traffic)
        return sim

    def as_dict(self) -> dict[str, Any]:
        """For results files."""
        return asdict(self)

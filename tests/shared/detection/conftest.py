"""Fixtures of the detector tests: one agent frame rendered by the lock-step simulation."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from shared.paths import DEFAULT_SCENE

RENDER_AGENT = "agent1"  # four cameras and two lidars
RENDER_SEED = 101  # a tuning seed: not one the int8 models were calibrated on
RENDER_VEHICLES = 16
RENDER_WARMUP_S = 5.0  # traffic spreads over the table first


@dataclass(frozen=True)
class AgentFrame:
    images: list[np.ndarray]  # (H, W, 3) uint8 RGB per camera, JPEG-decoded as the MEC gets them
    cloud: np.ndarray  # (N, 4) merged lidar cloud in the agent frame (the detector's input)


@pytest.fixture(scope="session")
def agent_frame() -> AgentFrame:
    """RENDER_AGENT's sensors after the warm-up: each one's first capture (the sensors fire within a
    few ticks of each other)."""
    from shared.perception.decode import image_to_array, point_cloud_to_array
    from shared.perception.lidar_preprocess import agent_frame_transforms, merge_clouds
    from shared.scene.scene import Scene
    from sim.config import load_sim_settings
    from sim.lockstep import LockstepSim

    scene = Scene.load(DEFAULT_SCENE)
    sensors = scene.sensors_of(RENDER_AGENT)
    T = agent_frame_transforms(scene, RENDER_AGENT)
    settings = load_sim_settings(vehicles=RENDER_VEHICLES, seed=RENDER_SEED)
    with LockstepSim(scene, settings, sensor_ids=[s.id for s in sensors]) as sim:
        for _ in range(round(RENDER_WARMUP_S * settings.tick_hz)):
            sim.traffic.step()
        captures: dict = {}
        for _ in range(round(settings.tick_hz)):  # every sensor fires within a second
            captures.update({c.spec.id: c for c in sim.step().captures})
            if all(s.id in captures for s in sensors):
                break
    images = [image_to_array(captures[s.id].message) for s in sensors if s.kind == "camera"]
    cloud = merge_clouds([(T[s], point_cloud_to_array(captures[s].message)) for s in T])
    return AgentFrame(images, cloud)

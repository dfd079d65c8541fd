"""Lock-step simulation: traffic and sensors in one process, one tick after the other, no wall clock.

Each `step()` advances the traffic one tick, builds that tick's ground truth and captures every sensor
that fires on it, so no frame is ever skipped and the run goes as fast as the CPU allows (datasets,
experiments, the sim bench). Stamps are `epoch_ns` + simulated time, so two runs with one seed and
one epoch produce identical ground truth and sensor data.

    with LockstepSim(scene, settings) as sim:
        for _ in range(600):
            tick = sim.step()          # tick.ground_truth, tick.captures
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from rmmdet.v1.sim_pb2 import GroundTruth

from shared.config import with_overrides
from shared.scene.model import SensorSpec
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.timebase import tick_stamp_ns
from sim.config import SimSettings
from sim.ground_truth import ground_truth_message
from sim.sensors.camera import Lighting
from sim.sensors.rig import Capture, SensorRig
from sim.traffic import TrafficSim


def override(
    spec: SensorSpec, rate_hz: dict[str, float] | None, model_overrides: dict[str, dict[str, Any]] | None
) -> SensorSpec:
    """`spec` with its kind's rate and model fields replaced (validated like the scene file)."""
    update: dict[str, Any] = {}
    if rate_hz and spec.kind in rate_hz:
        update["rate_hz"] = rate_hz[spec.kind]
    if model_overrides and spec.kind in model_overrides:
        update[spec.kind] = model_overrides[spec.kind]
    return with_overrides(spec, update) if update else spec


@dataclass(frozen=True)
class Tick:
    ground_truth: GroundTruth
    captures: list[Capture]
    step_ns: int  # wall time of the traffic step + ground-truth message


class LockstepSim:
    """Traffic of `settings` on `scene` with the sensors `sensor_ids` (default: all of the scene)."""

    def __init__(
        self,
        scene: Scene,
        settings: SimSettings,
        sensor_ids: list[str] | None = None,
        epoch_ns: int = 0,
        labels: bool = False,
        rate_hz: dict[str, float] | None = None,
        model_overrides: dict[str, dict[str, Any]] | None = None,
        lighting: Lighting | None = None,
    ) -> None:
        """`rate_hz` overrides the capture rate per sensor kind, e.g. {"camera": 2.0} for a dataset
        that does not want 15 near-identical frames a second; `model_overrides` updates fields of a
        kind's sensor model, e.g. {"lidar": {"range_noise_std_m": 0.01}}; `lighting` replaces the
        cameras' default lighting."""
        self.scene = scene
        self.settings = settings
        self.epoch_ns = epoch_ns
        self.labels = labels
        self.traffic = TrafficSim(
            scene, RoadNetwork(scene), settings.traffic, settings.seed, settings.tick_hz
        )
        specs = list(scene.spec.sensors) if sensor_ids is None else [scene.sensor(s) for s in sensor_ids]
        specs = [override(s, rate_hz, model_overrides) for s in specs]
        self.rig = SensorRig(scene, specs, lighting, settings.world)

    def ground_truth(self) -> GroundTruth:
        """Ground truth of the current tick, stamped with the epoch + simulated time."""
        msg = ground_truth_message(self.traffic, self.scene, self.settings.seed, self.settings.tick_hz)
        msg.header.tick = self.traffic.tick
        msg.header.epoch = self.epoch_ns
        msg.header.frame_id = "world"
        msg.header.stamp.FromNanoseconds(
            tick_stamp_ns(self.epoch_ns, self.traffic.tick, self.settings.tick_hz)
        )
        return msg

    def step(self) -> Tick:
        t0 = time.perf_counter_ns()
        self.traffic.step()
        gt = self.ground_truth()
        step_ns = time.perf_counter_ns() - t0
        return Tick(gt, self.rig.capture(gt, labels=self.labels), step_ns)

    def close(self) -> None:
        self.rig.close()

    def __enter__(self) -> LockstepSim:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

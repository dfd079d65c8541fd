"""The MEC's camera cadence: with a lidar live the camera detector runs on every n-th frame only; on
sim ticks those are the frames `frame_due` names (the ones the MEC asks its cameras to capture)."""

from __future__ import annotations

import numpy as np
import pytest

from shared.perception.config import MecSettings
from shared.perception.pipeline import AgentInputs, AgentPipeline
from shared.scene.scene import Scene
from sim.config import DEFAULT_SCENE

TICK_HZ = 60.0
TICKS_PER_FRAME = 6  # 10 Hz sensors


class CountingCameras:
    name = "counting"

    def __init__(self) -> None:
        self.calls: list[int] = []

    def detect(self, images: list[np.ndarray]) -> list[np.ndarray]:
        self.calls.append(len(images))
        return [np.zeros((0, 6), np.float32) for _ in images]


class NoCars:
    name = "no-cars"

    def detect(self, points: np.ndarray) -> np.ndarray:
        return np.zeros((0, 9), np.float32)


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.load(DEFAULT_SCENE)


def pipeline(scene: Scene, cameras: CountingCameras) -> AgentPipeline:
    return AgentPipeline(scene, "agent1", MecSettings(), cameras=cameras, lidar=NoCars())


def frame(scene: Scene, tick: int, lidar: bool) -> AgentInputs:
    inputs = AgentInputs(stamp_ns=round(tick / TICK_HZ * 1e9), tick=tick)
    for cam in scene.sensors_of("agent1", "camera"):
        inputs.add("camera", cam.id, np.zeros((48, 64, 3), np.uint8))
    if lidar:
        for lid in scene.sensors_of("agent1", "lidar"):
            inputs.add("lidar", lid.id, np.zeros((0, 4), np.float32))
    return inputs


def test_on_sim_ticks_the_detector_runs_where_the_demanded_frames_fall(scene: Scene) -> None:
    cams = CountingCameras()
    pipe = pipeline(scene, cams)
    pipe.tick_hz = TICK_HZ
    n = MecSettings().detectors.camera_every_n_with_lidar
    assert n > 1
    ticks = [k * TICKS_PER_FRAME for k in range(1, 3 * n + 1)]  # starts off the cadence's phase
    ran = []
    for tick in ticks:
        before = len(cams.calls)
        pipe.process(frame(scene, tick, lidar=True))
        ran.append(len(cams.calls) > before)
    assert [t for t, r in zip(ticks, ran, strict=True) if r] == [t for t in ticks if t % (n * 6) == 0]
    assert pipe.cameras_due(True, 5 * TICKS_PER_FRAME) == frozenset(pipe.camera_ids)
    assert pipe.cameras_due(True, 6 * TICKS_PER_FRAME) == frozenset()


def test_without_a_lidar_every_frame_runs_the_detector(scene: Scene) -> None:
    cams = CountingCameras()
    pipe = pipeline(scene, cams)
    pipe.tick_hz = TICK_HZ
    for k in range(1, 6):
        pipe.process(frame(scene, k * TICKS_PER_FRAME, lidar=False))
    assert cams.calls == [4] * 5


def test_without_ticks_every_nth_processed_frame_runs_the_detector(scene: Scene) -> None:
    cams = CountingCameras()
    pipe = pipeline(scene, cams)  # real sensors: no tick rate
    n = MecSettings().detectors.camera_every_n_with_lidar
    for _ in range(2 * n):
        pipe.process(frame(scene, 0, lidar=True))
    assert len(cams.calls) == 2

"""The background lidar detector on the simulated real-size intersection: trees, poles, signs and signal
heads never become vehicles, with the background model (learned online) and by the detector's own
gates from the scene's vehicle classes alone."""

from __future__ import annotations

import numpy as np
import pytest

from shared.perception.config import MecSettings
from shared.perception.core import MecCore
from shared.perception.pipeline import AgentPipeline
from shared.scene.scene import Scene
from sim.config import load_sim_settings
from sim.lockstep import LockstepSim
from sim.sensors.lidar import LidarScan
from studies.evaluation.fusion import feed_tick
from tests.helpers import FULL_SCALE_SCENE

LIDAR = "lidar_11"
SCENERY = ("tree", "pole", "sign", "signal")  # static objects by id prefix (not buildings)
NEAR_M = 3.0  # a detection this close to a piece of scenery is taken for it


@pytest.fixture(scope="module")
def site() -> Scene:
    return Scene.load(FULL_SCALE_SCENE)


def scenery_xy(scene: Scene) -> np.ndarray:
    return np.array([o.position_m[:2] for o in scene.spec.static_objects if o.id.startswith(SCENERY)])


def test_an_empty_crossing_gives_no_detection_and_no_track_after_warm_up(site: Scene) -> None:
    settings = load_sim_settings(scene=str(FULL_SCALE_SCENE), seed=0, vehicles=0)
    core = MecCore(site, "agent1", MecSettings(detectors={"lidar": "background"}), sensor_ids=[LIDAR])
    core.tick_hz = settings.tick_hz
    warm_up = core.pipeline.backgrounds[LIDAR].config.warmup_frames
    boxes, tracks, frames = 0, 0, 0
    with LockstepSim(site, settings, sensor_ids=[LIDAR]) as sim:
        while frames < warm_up + 20:
            tick = sim.step()
            if not tick.captures:
                continue
            gt = tick.ground_truth
            out = feed_tick(core, gt.header.stamp.ToNanoseconds(), gt.header.tick, tick.captures)
            assert out is not None
            frames += 1
            if frames > warm_up:
                boxes += len(out.result.lidar_boxes_world)
                tracks += len(out.result.tracks)
    assert core.pipeline.backgrounds[LIDAR].ready
    assert (boxes, tracks) == (0, 0)


def test_without_a_background_the_class_gates_alone_reject_the_scenery(site: Scene) -> None:
    # Every static point straight into the cluster detector: trees (7 m tall, 4 m crowns), sign posts,
    # signal masts with their arms fit no vehicle class of the scene. (Building walls cut by the view
    # can look like a truck's side: that is the background model's to remove.)
    settings = load_sim_settings(scene=str(FULL_SCALE_SCENE), seed=0, vehicles=0)
    scan = None
    with LockstepSim(site, settings, sensor_ids=[LIDAR]) as sim:
        while scan is None:
            for capture in sim.step().captures:
                assert isinstance(capture.data, LidarScan)
                scan = capture.data
    pipeline = AgentPipeline(
        site, "agent1", MecSettings(detectors={"lidar": "background"}), sensor_ids=[LIDAR]
    )
    T = pipeline.lidar_T[LIDAR]
    xyz = np.asarray(scan.points_m, float) @ T[:3, :3].T + T[:3, 3]
    assert pipeline.lidar_detector is not None
    boxes = pipeline.lidar_detector.detect(np.column_stack([xyz, np.zeros(len(xyz))]))
    world_xy = boxes[:, :2] + pipeline.origin_m[:2]
    nearest = np.linalg.norm(world_xy[:, None, :] - scenery_xy(site)[None, :, :], axis=2).min(
        axis=1, initial=1e9
    )
    assert (nearest > NEAR_M).all(), world_xy[nearest <= NEAR_M]

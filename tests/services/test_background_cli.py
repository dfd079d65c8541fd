"""`rmmdet background learn`: a site's lidar backgrounds learned from a simulated or recorded period, saved
where the MEC starts from them (no warm-up), with the same foreground as the model learned in memory."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from services.cli.background import simulated
from services.cli.main import app
from shared.perception.background import (
    BackgroundConfig,
    RangeBackground,
    RangeImage,
    learn_period,
    model_path,
)
from shared.perception.config import MecSettings
from shared.perception.decode import point_cloud_message
from shared.perception.pipeline import AgentPipeline
from shared.recording.record import encoding_of
from shared.recording.writer import RecordingWriter
from shared.scene.scene import Scene
from sim.config import load_sim_settings
from sim.lockstep import LockstepSim
from sim.sensors.lidar import LidarScan
from tests.helpers import FULL_SCALE_SCENE

LIDAR = "lidar_11"
PERIOD_S = 2.0  # 20 revolutions at 10 Hz: enough for the ground, poles and trees of an empty crossing
NS_PER_S = 10**9
CLOUD = encoding_of("foxglove.PointCloud")


@pytest.fixture(scope="module")
def site() -> Scene:
    return Scene.load(FULL_SCALE_SCENE)


def traffic_scan(scene: Scene, seconds: float = 3.0) -> LidarScan:
    """The lidar's revolution after `seconds` of traffic (cars in view)."""
    settings = load_sim_settings(scene=str(FULL_SCALE_SCENE), seed=101)
    scan = None
    with LockstepSim(scene, settings, sensor_ids=[LIDAR]) as sim:
        for _ in range(round(seconds * settings.tick_hz)):
            for capture in sim.step().captures:
                assert isinstance(capture.data, LidarScan)
                scan = capture.data
    assert scan is not None
    return scan


def test_learned_saved_and_loaded_at_start_with_the_same_foreground(site: Scene, tmp_path: Path) -> None:
    result = CliRunner().invoke(
        app,
        [
            "background",
            "learn",
            "--scene",
            str(FULL_SCALE_SCENE),
            "--duration-s",
            str(PERIOD_S),
            "--out",
            str(tmp_path),
        ],
    )
    assert result.exit_code == 0, result.output
    saved = model_path(tmp_path, site.scene_id, LIDAR)
    assert saved.is_file() and f"{LIDAR}: 20 revolutions" in result.output
    # The MEC finds it under its models_dir and starts ready: no warm-up.
    mec = MecSettings(detectors={"lidar": "background", "background": {"models_dir": tmp_path}})
    started = AgentPipeline(site, "agent1", mec, sensor_ids=[LIDAR]).backgrounds[LIDAR]
    assert started.ready and started.frames == mec.detectors.background.warmup_frames
    # The same period learned in memory classifies a revolution with traffic the same way.
    layouts = {LIDAR: RangeImage.of(site.sensor(LIDAR).lidar)}  # type: ignore[arg-type]
    period = simulated(FULL_SCALE_SCENE, site, [LIDAR], PERIOD_S, 0, 0)
    in_memory = learn_period(layouts, BackgroundConfig(), period)[LIDAR]
    scan = traffic_scan(site)
    xyz = np.asarray(scan.points_m, float)
    front = started.foreground(xyz, learn=False)
    np.testing.assert_array_equal(front, in_memory.foreground(xyz, learn=False))
    cars = scan.vehicle_ids != ""
    assert cars.sum() > 100 and front[cars].mean() > 0.95  # the cars stand out of the learned scene
    assert front[~cars].mean() < 0.005  # ground, poles, trees and signs are background at once


def test_learned_from_a_recording_as_from_the_sim(site: Scene, tmp_path: Path) -> None:
    recording = tmp_path / "empty.mcap"
    period = list(simulated(FULL_SCALE_SCENE, site, [LIDAR], PERIOD_S, 0, 0))
    with RecordingWriter(recording) as writer:
        for k, (lidar_id, xyz) in enumerate(period):
            msg = point_cloud_message(xyz.astype(np.float32), np.ones(len(xyz), np.float32), lidar_id, k)
            stamp = k * NS_PER_S // 10
            payload = msg.SerializeToString()
            writer.write(f"rmmdet/sensors/{lidar_id}", CLOUD, payload, None, stamp, stamp)
    result = CliRunner().invoke(
        app,
        [
            "background",
            "learn",
            "--scene",
            str(FULL_SCALE_SCENE),
            "--recording",
            str(recording),
            "--out",
            str(tmp_path / "models"),
        ],
    )
    assert result.exit_code == 0, result.output
    layout = RangeImage.of(site.sensor(LIDAR).lidar)  # type: ignore[arg-type]
    model = RangeBackground(layout, BackgroundConfig(), model_path(tmp_path / "models", site.scene_id, LIDAR))
    direct = learn_period({LIDAR: layout}, BackgroundConfig(), iter(period))[LIDAR]
    np.testing.assert_array_equal(model.background_bin, direct.background_bin)


def test_a_scene_without_the_agent_is_refused(tmp_path: Path) -> None:
    result = CliRunner().invoke(
        app,
        [
            "background",
            "learn",
            "--scene",
            str(FULL_SCALE_SCENE),
            "--agent",
            "agent9",
            "--out",
            str(tmp_path),
        ],
    )
    assert result.exit_code == 2 and "no lidar of ['agent9']" in result.output


@pytest.mark.parametrize("damage", ["another layout", "not a model"])
def test_a_saved_model_that_does_not_fit_is_refused_and_the_lidar_learns_online(
    site: Scene, tmp_path: Path, damage: str, caplog: pytest.LogCaptureFixture
) -> None:
    """A site whose lidar was changed after its background was saved (or whose file is damaged): the MEC
    starts, names the refused file and learns that lidar's background online."""
    saved = model_path(tmp_path, site.scene_id, LIDAR)
    saved.parent.mkdir(parents=True)
    if damage == "another layout":
        layout = RangeImage.of(site.sensor(LIDAR).lidar)  # type: ignore[arg-type]
        half = RangeImage(
            layout.elevations_rad[::2], layout.azimuth_bins, layout.min_range_m, layout.max_range_m
        )
        RangeBackground(half, BackgroundConfig()).save(saved)
        assert saved.is_file()
    else:
        saved.write_bytes(b"PK\x03\x04 not a model")
    mec = MecSettings(detectors={"lidar": "background", "background": {"models_dir": tmp_path}})
    with caplog.at_level("WARNING", logger="shared.perception.background"):
        pipeline = AgentPipeline(site, "agent1", mec, sensor_ids=[LIDAR])
    started = pipeline.backgrounds[LIDAR]
    assert started.refused_model == saved and not started.ready and started.frames == 0
    assert pipeline.counts["rejected/background_model"] == 1  # in the health report's rejections
    assert any(str(saved) in r.getMessage() and "learning online" in r.getMessage() for r in caplog.records)

"""Sensor rig and lock-step runs: firing schedule, determinism, message contents, MCAP round trip."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from google.protobuf.message import Message
from rmmdet.v1.sensors_pb2 import RadarScan

from shared.bus.codec import encode
from shared.bus.streams import SENSOR_STREAM, get_stream
from shared.perception.decode import point_cloud_to_array as from_point_cloud
from shared.recording.reader import decode_record, read_records
from shared.recording.record import Record
from shared.recording.writer import RecordingWriter
from shared.scene.cadence import fires
from shared.scene.scene import Scene
from sim.config import SimSettings
from sim.lockstep import LockstepSim, Tick
from sim.sensors.camera import CameraFrame, Lighting
from sim.sensors.lidar import LidarScan
from sim.sensors.rig import CameraSensor, LidarSensor, sensor_rng

TICK_HZ = 60.0
RUN_TICKS = 24  # 0.4 s: every sensor fires several times


def run(scene: Scene, seed: int, ticks: int = RUN_TICKS, labels: bool = False) -> list[Tick]:
    settings = SimSettings(seed=seed, tick_hz=TICK_HZ)
    with LockstepSim(scene, settings, labels=labels) as sim:
        return [sim.step() for _ in range(ticks)]


@pytest.fixture(scope="module")
def ticks(scene: Scene) -> list[Tick]:
    return run(scene, seed=3)


def test_sensor_fires_at_its_rate_on_the_first_tick_of_each_period() -> None:
    for rate_hz, first_ticks in ((15, [0, 4, 8, 12]), (10, [0, 6, 12]), (20, [0, 3, 6, 9, 12])):
        fired = [t for t in range(13) if fires(rate_hz, t, TICK_HZ)]
        assert fired == first_ticks
        assert sum(fires(rate_hz, t, TICK_HZ) for t in range(600)) == rate_hz * 10


def test_noise_generator_depends_only_on_seed_sensor_and_tick() -> None:
    a = sensor_rng(1, "cam_11", 5).normal(size=4)
    assert np.array_equal(a, sensor_rng(1, "cam_11", 5).normal(size=4))
    for other in (sensor_rng(2, "cam_11", 5), sensor_rng(1, "cam_12", 5), sensor_rng(1, "cam_11", 6)):
        assert not np.array_equal(a, other.normal(size=4))


def test_every_sensor_captures_at_its_rate_with_the_tick_stamp(scene: Scene, ticks: list[Tick]) -> None:
    counts = Counter(c.spec.id for t in ticks for c in t.captures)
    for spec in scene.spec.sensors:
        expected = sum(fires(spec.rate_hz, t.ground_truth.header.tick, TICK_HZ) for t in ticks)
        assert counts[spec.id] == expected > 0, spec.id
    for t in ticks:
        stamp = t.ground_truth.header.stamp.ToNanoseconds()
        assert stamp == round(t.ground_truth.header.tick / TICK_HZ * 1e9)
        for c in t.captures:
            assert c.stamp_ns == stamp
            if c.spec.kind != "radar":  # foxglove messages stamp themselves; RadarScan gets the bus header
                assert c.message.timestamp.ToNanoseconds() == stamp


def test_one_seed_gives_identical_ground_truth_and_sensor_data(scene: Scene, ticks: list[Tick]) -> None:
    again = run(scene, seed=3)
    for a, b in zip(ticks, again, strict=True):
        assert a.ground_truth.SerializeToString() == b.ground_truth.SerializeToString()
        assert [c.message.SerializeToString() for c in a.captures] == [
            c.message.SerializeToString() for c in b.captures
        ]
    other = run(scene, seed=4, ticks=2)
    assert other[1].ground_truth.SerializeToString() != ticks[1].ground_truth.SerializeToString()


def test_messages_carry_the_captured_data(ticks: list[Tick]) -> None:
    kinds = set()
    for t in ticks:
        for c in t.captures:
            kinds.add(c.spec.kind)
            if c.spec.kind == "lidar":
                assert isinstance(c.message, PointCloud) and isinstance(c.data, LidarScan)
                cloud = from_point_cloud(c.message)
                assert np.array_equal(cloud[:, :3], c.data.points_m)
                assert len(cloud) > 1000  # the static scene alone returns thousands of points
            elif c.spec.kind == "radar":
                assert isinstance(c.message, RadarScan) and isinstance(c.data, list)
                assert [x.range_m for x in c.message.targets] == pytest.approx([x.range_m for x in c.data])
            else:
                assert isinstance(c.message, CompressedImage) and isinstance(c.data, CameraFrame)
                image = cv2.imdecode(np.frombuffer(c.message.data, np.uint8), cv2.IMREAD_COLOR)
                assert image.shape == (*c.data.rgb.shape[:2], 3)
                # JPEG is lossy; the decoded frame stays close to the rendered one
                diff = np.abs(image[:, :, ::-1].astype(int) - c.data.rgb.astype(int))
                assert diff.mean() < 4.0
    assert kinds == {"camera", "lidar", "radar"}


def test_labels_do_not_change_the_images(scene: Scene, ticks: list[Tick]) -> None:
    labelled = run(scene, seed=3, ticks=9, labels=True)
    seen_vehicle = False
    for a, b in zip(ticks, labelled, strict=False):
        for ca, cb in zip(a.captures, b.captures, strict=True):
            if ca.spec.kind != "camera":
                continue
            assert isinstance(ca.data, CameraFrame) and isinstance(cb.data, CameraFrame)
            assert np.array_equal(ca.data.rgb, cb.data.rgb)
            assert ca.data.visible_boxes == {}  # live stream: no labels computed
            seen_vehicle |= bool(cb.data.visible_boxes)
    assert seen_vehicle


def records(ticks: list[Tick]) -> Iterator[tuple[Record, Message]]:
    """Each tick's ground truth and captures as the bus carries them, logged at the tick stamp."""
    for t in ticks:
        stamp = t.ground_truth.header.stamp.ToNanoseconds()
        gt = encode(t.ground_truth)
        key = get_stream("ground_truth").key()
        yield Record(key, str(gt.encoding), gt.payload, None, stamp, stamp), t.ground_truth
        for c in t.captures:
            key = get_stream(SENSOR_STREAM[c.spec.kind]).key(agent=c.spec.agent, sensor=c.spec.id)
            enc = encode(c.message)
            yield Record(key, str(enc.encoding), enc.payload, enc.attachment, stamp, stamp), c.message


def test_sim_streams_survive_an_mcap_round_trip(tmp_path: Path, ticks: list[Tick]) -> None:
    path = tmp_path / "sim.mcap"
    written = list(records(ticks))
    with RecordingWriter(path) as writer:
        for record, _ in written:
            writer.write_record(record)
    back = list(read_records(path))
    assert len(back) == len(written)
    for got, (record, message) in zip(back, written, strict=True):
        assert (got.key, got.payload, got.log_time_ns) == (record.key, record.payload, record.log_time_ns)
        assert decode_record(got).message == message


def test_rate_overrides_change_how_often_a_kind_captures(scene: Scene) -> None:
    settings = SimSettings(seed=3, tick_hz=TICK_HZ)
    with LockstepSim(scene, settings, sensor_ids=["cam_11", "lidar_11"], rate_hz={"camera": 5.0}) as sim:
        counts = Counter(c.spec.id for _ in range(60) for c in sim.step().captures)
    assert counts == {"cam_11": 5, "lidar_11": 10}  # ticks 1..60: camera every 12th, lidar (10 Hz) every 6th


def test_model_overrides_and_lighting_reach_the_sensors(scene: Scene) -> None:
    """The dataset's and the evaluation's per-seed conditions (noise, lighting) must reach the rig."""
    settings = SimSettings(seed=3, tick_hz=TICK_HZ)
    light = Lighting(direction=(0.0, 0.6, 0.8), ambient=0.4, diffuse=0.5)
    overrides = {"camera": {"image_noise_std": 0.02}, "lidar": {"range_noise_std_m": 0.01}}
    with LockstepSim(
        scene, settings, sensor_ids=["cam_11", "lidar_11"], model_overrides=overrides, lighting=light
    ) as sim:
        camera, lidar = sim.rig.sensors["cam_11"], sim.rig.sensors["lidar_11"]
        assert isinstance(camera, CameraSensor) and isinstance(lidar, LidarSensor)
        assert camera.noise_std == 0.02 and camera.renderer.lighting == light
        assert lidar.simulator.model.range_noise_std_m == 0.01
        plain = scene.sensor("lidar_11").lidar  # the scene's own model is left alone
        assert plain is not None and plain.range_noise_std_m != 0.01

"""MecCore, the MEC's bus-free core: join, input health, status hysteresis, cadence and rejections, driven
the way the service and the studies drive it (sensor messages in, one output per agent frame)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from rmmdet.v1.perception_pb2 import PerceptionStatus

from shared.bus.health import NOMINAL
from shared.paths import DEFAULT_SCENE
from shared.perception.config import DetectorsConfig, MecSettings, SyncConfig
from shared.perception.core import MecCore, default_trigger
from shared.perception.inputs import Status
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from sim.sensors.lidar import LidarScan, to_point_cloud
from tests.shared.perception.stubs import CountingCameras, NoCars

TICK_HZ = 60.0
TICKS_PER_FRAME = 6  # 10 Hz sensors
AGENT = "agent1"  # 4 cameras, 2 lidars


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.load(DEFAULT_SCENE)


def settings(**sync: object) -> MecSettings:
    # Every camera every frame: the join then waits for all six sensors on each tick.
    return MecSettings(
        detectors=DetectorsConfig(camera_every_n_with_lidar=1),
        sync=SyncConfig(**sync),  # type: ignore[arg-type]
    )


def core_of(scene: Scene, cfg: MecSettings | None = None, cameras: CountingCameras | None = None) -> MecCore:
    return MecCore(scene, AGENT, cfg or settings(), cameras=cameras or CountingCameras(), lidar=NoCars())


def jpeg() -> CompressedImage:
    """An image of the agent's cameras' calibrated size (448 x 336 px): another size is refused."""
    ok, buf = cv2.imencode(".jpg", np.full((336, 448, 3), 90, np.uint8))
    assert ok
    return CompressedImage(format="jpeg", data=buf.tobytes())


def cloud(stamp_ns: int) -> PointCloud:
    none_f, none_i = np.zeros(0, np.float32), np.zeros(0, np.int32)
    scan = LidarScan("lidar", np.zeros((0, 3), np.float32), none_f, np.zeros(0, str), none_i, none_i, none_f)
    return to_point_cloud(scan, "lidar", stamp_ns)


def feed(core: MecCore, frame: int, skip: tuple[str, ...] = (), late_s: float = 0.001) -> float:
    """Every sensor of frame `frame` (but `skip`) arrives `late_s` after its stamp; returns the clock."""
    tick = frame * TICKS_PER_FRAME
    stamp_ns = round(tick / TICK_HZ * NS_PER_S)
    now_s = stamp_ns / NS_PER_S + late_s
    for sensor_id, kind in core.kinds.items():
        if sensor_id in skip:
            continue
        msg = jpeg() if kind == "camera" else cloud(stamp_ns)
        assert core.receive(sensor_id, stamp_ns, tick, msg, now_s, round(now_s * NS_PER_S)) is None
    return now_s


def test_a_complete_frame_is_processed_at_once_and_published_full(scene: Scene) -> None:
    cams = CountingCameras()
    core = core_of(scene, cameras=cams)
    now = feed(core, 1)
    out = core.step(now)
    assert out is not None and out.frame.tick == TICKS_PER_FRAME and out.frame.missing == ()
    assert out.status is Status.FULL and out.message.status == PerceptionStatus.PERCEPTION_STATUS_FULL
    assert out.message.agent_id == AGENT and {i.sensor_id for i in out.message.inputs} == set(core.kinds)
    assert set(out.inputs.images) == {s for s, k in core.kinds.items() if k == "camera"}
    assert cams.calls == [1, 1, 1, 1]  # each image detected on arrival, reused by the frame
    assert out.result.latencies_s["detect_2d_ahead"] > 0
    assert core.step(now) is None  # nothing new
    assert core.counters["frames/published"] == 1


def test_a_silent_sensor_degrades_the_output_and_recovery_needs_complete_frames(scene: Scene) -> None:
    cfg = settings()
    core = core_of(scene, cfg)
    statuses = []
    for frame in range(1, 12):
        now = feed(core, frame, skip=("lidar_12",) if 2 <= frame <= 6 else ())
        out = core.step(now + cfg.sync.max_wait_s)  # a frame missing a live sensor goes out at the wait
        assert out is not None
        statuses.append(out.status)
    recover = cfg.health.recover_frames
    assert statuses[:1] == [Status.FULL]
    assert statuses[1:6] == [Status.DEGRADED] * 5
    # Frame 7: the sensor is back, but MISSING sensors are not waited for, so its frame completed
    # without it and its sample came late (counted). Then `recover` complete frames: FULL (hysteresis).
    assert core.counts()["late/lidar_12"] == 1
    assert statuses[6 : 7 + recover - 1] == [Status.DEGRADED] * recover
    assert statuses[7 + recover - 1 :] == [Status.FULL] * (len(statuses) - 6 - recover)
    level, text = core.health(now)
    assert level == NOMINAL and text.startswith("full")


def test_a_sensor_whose_process_left_is_not_waited_for(scene: Scene) -> None:
    core = core_of(scene)
    core.step(feed(core, 1))
    core.mark_gone("lidar_12")
    now = feed(core, 2, skip=("lidar_12",))
    out = core.step(now)  # no wait: the gone sensor is not expected
    assert out is not None and out.status is Status.DEGRADED and not out.fused["lidar_12"]
    assert "lidar_12: missing" in core.health(now)[1]


def test_stale_and_unknown_inputs_are_rejected_and_counted(scene: Scene) -> None:
    cfg = settings()
    core = core_of(scene, cfg)
    stamp_ns = TICKS_PER_FRAME * NS_PER_S // 60
    late_ns = stamp_ns + round((cfg.health.max_age_s + 0.05) * NS_PER_S)
    assert (
        core.receive("lidar_11", stamp_ns, TICKS_PER_FRAME, cloud(stamp_ns), late_ns / NS_PER_S, late_ns)
        == "stale"
    )
    assert (
        core.receive("cam_99", stamp_ns, TICKS_PER_FRAME, jpeg(), late_ns / NS_PER_S, stamp_ns)
        == "unknown_sensor"
    )
    assert core.counters["stale/lidar_11"] == 1 and core.counters["rejected/unknown_sensor"] == 1


def test_an_undecodable_image_is_left_out_of_its_frame_and_counted(scene: Scene) -> None:
    core = core_of(scene)
    tick = TICKS_PER_FRAME
    stamp_ns = round(tick / TICK_HZ * NS_PER_S)
    now = stamp_ns / NS_PER_S
    for sensor_id, kind in core.kinds.items():
        msg = CompressedImage(format="jpeg", data=b"not a jpeg") if sensor_id == "cam_11" else None
        msg = msg or (jpeg() if kind == "camera" else cloud(stamp_ns))
        core.receive(sensor_id, stamp_ns, tick, msg, now, stamp_ns)
    out = core.step(now)
    assert out is not None and "cam_11" not in out.inputs.images and not out.fused["cam_11"]
    assert core.counters["rejected/camera_decode"] == 1


def test_a_pipeline_failure_is_counted_and_the_next_frame_goes_on(scene: Scene) -> None:
    cams = CountingCameras(fail=True)
    core = core_of(scene, cameras=cams)
    assert core.step(feed(core, 1)) is None
    assert core.counters["errors/pipeline"] == 1 and core.counters["errors/detect_ahead"] == 4
    cams.fail = False
    assert core.step(feed(core, 2)) is not None


def test_under_a_sim_the_cameras_are_asked_for_every_nth_frame_while_a_lidar_is_live(scene: Scene) -> None:
    core = MecCore(scene, AGENT, MecSettings(), cameras=CountingCameras(), lidar=NoCars())
    assert core.cadence(0.0) == (1, False)  # real sensors: no demand
    core.tick_hz = TICK_HZ
    n = MecSettings().detectors.camera_every_n_with_lidar
    assert core.cadence(0.0) == (n, True) and core.cadence(0.0) == (n, False)
    assert core.rates_hz()["cam_11"] == pytest.approx(10.0 / n)


def test_bounded_wait_joins_asynchronous_sensors_by_stamp(scene: Scene) -> None:
    """Real sensors: no ticks (0 on every message), stamps of their own; the lidar triggers a frame and
    each camera joins with its image nearest in time, or is left out after the wait."""
    cfg = settings(collector="bounded_wait", tolerance_s=0.04, max_wait_s=0.1)
    core = core_of(scene, cfg)
    assert default_trigger(core.kinds) == "lidar_11"
    t0 = 5 * NS_PER_S
    for sensor_id, kind in core.kinds.items():
        offset = {"lidar_11": 0, "lidar_12": 0.012}.get(sensor_id, 0.021)
        stamp = t0 + round(offset * NS_PER_S)
        msg = jpeg() if kind == "camera" else cloud(stamp)
        core.receive(sensor_id, stamp, 0, msg, stamp / NS_PER_S + 0.005, stamp + 5_000_000)
    out = core.step(t0 / NS_PER_S + 0.03)
    assert out is not None and out.frame.stamp_ns == t0 and out.frame.missing == ()
    assert set(out.frame.samples) == set(core.kinds)
    # Next frame: cam_14 never comes; the frame leaves without it once its wait is over.
    t1 = t0 + NS_PER_S // 10
    for sensor_id, kind in core.kinds.items():
        if sensor_id != "cam_14":
            core.receive(sensor_id, t1, 0, jpeg() if kind == "camera" else cloud(t1), t1 / NS_PER_S, t1)
    assert core.step(t1 / NS_PER_S + 0.05) is None
    out = core.step(t1 / NS_PER_S + 0.11)
    assert out is not None and out.frame.missing == ("cam_14",) and out.status is Status.DEGRADED


def test_an_unknown_trigger_is_refused(scene: Scene) -> None:
    with pytest.raises(ValueError, match="trigger"):
        core_of(scene, settings(collector="bounded_wait", trigger="cam_99"))


def test_after_its_lidars_are_lost_each_frame_tick_goes_out_while_the_cameras_catch_up(scene: Scene) -> None:
    """Cameras at every 10th frame (lidars live), then both lidars' process leaves: the cameras are
    asked for every frame, but they last delivered up to 1 s ago at the old cadence and take a frame to
    follow. They are not missing for that (judged at the new rate from the change on), so the frame tick
    meanwhile goes out coasted instead of leaving a gap in the agent's output."""
    core = MecCore(scene, AGENT, MecSettings(), cameras=CountingCameras(), lidar=NoCars())
    core.tick_hz = TICK_HZ
    core.reset(0.0)
    n = MecSettings().detectors.camera_every_n_with_lidar
    for frame in range(1, n):
        due = core.pipeline.cameras_due(True, frame * TICKS_PER_FRAME)
        now = feed(core, frame, skip=tuple(c for c in core.camera_ids if c not in due))
        core.cadence(now)
        assert core.step(now) is not None
    lidars = tuple(s for s, k in core.kinds.items() if k == "lidar")
    for lidar in lidars:
        core.mark_gone(lidar)
    assert core.cadence(now + 0.05) == (1, True)
    stamp_s = n * TICKS_PER_FRAME / TICK_HZ  # nothing delivered: the cameras have not followed yet
    out = core.step(stamp_s + MecSettings().sync.max_wait_s + 0.001)
    assert out is not None and out.frame.coasted and out.frame.tick == n * TICKS_PER_FRAME
    assert set(out.frame.missing) == set(core.camera_ids) and out.status is Status.UNAVAILABLE
    out = core.step(feed(core, n + 1, skip=lidars))
    assert out is not None and set(out.frame.samples) == set(core.camera_ids)
    assert out.frame.tick == (n + 1) * TICKS_PER_FRAME and out.status is Status.DEGRADED

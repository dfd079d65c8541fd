"""Sensor rig: a set of simulated sensors fed one ground-truth tick at a time. No bus inside.

The sensor service wraps one rig per sensor group (one process per group, so a group can be killed
alone); lock-step runs (datasets, experiments, the sim bench) hold one rig with every sensor of the
scene in-process. A sensor at rate r fires on the first tick of each 1/r period (its agent's
`sensor_phase_ticks` later: `Scene.captures_on`), so every sensor that fires on a tick sees that tick's
world and carries its stamp. Noise is drawn from a generator seeded by
(scenario seed, sensor id, tick): the same seed gives the same data whatever the timing or the split of
sensors into processes.

Each capture keeps the raw data and its ground-truth labels (camera: per-vehicle visible boxes; lidar:
the vehicle each point hit; radar: the vehicle or clutter behind each target); `message()` encodes it
for the bus (camera `foxglove.CompressedImage` JPEG, lidar `foxglove.PointCloud`, radar
`rmmdet.v1.RadarScan`).
"""

from __future__ import annotations

import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Protocol

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from google.protobuf.message import Message
from rmmdet.v1.sim_pb2 import GroundTruth

from shared.scene.model import SensorSpec
from shared.scene.scene import Scene
from sim.config import WorldSettings
from sim.ground_truth import poses_from_ground_truth
from sim.sensors.camera import CameraFrame, CameraRenderer, Lighting, add_noise, vehicles_box_corners
from sim.sensors.lidar import LidarScan, LidarSimulator, to_point_cloud
from sim.sensors.radar import RadarSimulator, SimRadarTarget, VehicleState, to_radar_scan
from sim.world import StaticWorld, VehiclePose, VehicleWorld

JPEG_QUALITY = 85


def sensor_rng(seed: int, sensor_id: str, tick: int) -> np.random.Generator:
    """Noise generator for one sensor frame: depends only on (seed, sensor, tick)."""
    return np.random.default_rng([seed, zlib.crc32(sensor_id.encode()), tick])


def encode_jpeg(rgb: np.ndarray, quality: int = JPEG_QUALITY) -> bytes:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return bytes(buf)


@dataclass(frozen=True)
class TickWorld:
    """What the sensors of one tick see: vehicle poses and states, and the tick's identity."""

    seed: int
    tick: int
    tick_hz: float
    stamp_ns: int
    poses: list[VehiclePose]
    states: list[VehicleState]  # same order as poses
    corners_w: np.ndarray  # (V, 8, 3) vehicle box corners, world

    @classmethod
    def from_ground_truth(cls, gt: GroundTruth, size_m: tuple[float, float, float]) -> TickWorld:
        poses = poses_from_ground_truth(gt)
        states = [
            VehicleState(
                vehicle_id=v.vehicle_id,
                center_m=np.array([v.box.center_m.x, v.box.center_m.y, v.box.center_m.z]),
                yaw_rad=v.box.yaw_rad,
                pitch_rad=v.pitch_rad,
                velocity_mps=np.array([v.velocity_mps.x, v.velocity_mps.y, v.velocity_mps.z]),
                size_m=pose.size_m,
            )
            for v, pose in zip(gt.vehicles, poses, strict=True)
        ]
        return cls(
            seed=gt.seed,
            tick=gt.header.tick,
            tick_hz=gt.tick_hz,
            stamp_ns=gt.header.stamp.ToNanoseconds(),
            poses=poses,
            states=states,
            corners_w=vehicles_box_corners(poses, size_m),
        )


@dataclass(frozen=True)
class Capture:
    """One sensor's output for one tick: raw data with labels, and its bus message."""

    spec: SensorSpec
    tick: int
    stamp_ns: int
    data: CameraFrame | LidarScan | list[SimRadarTarget]
    message: Message
    start_ns: int = 0  # wall clock around the capture (processing stamps)
    end_ns: int = 0


class Sensor(Protocol):
    spec: SensorSpec

    def capture(self, world: TickWorld, labels: bool) -> Capture: ...


class CameraSensor:
    def __init__(
        self,
        scene: Scene,
        spec: SensorSpec,
        static: StaticWorld,
        vehicles: VehicleWorld,
        lighting: Lighting = Lighting(),  # noqa: B008 (frozen dataclass)
    ) -> None:
        assert spec.camera is not None
        self.spec = spec
        self.renderer = CameraRenderer(scene, spec.id, static, vehicles, lighting, spec.camera)
        self.noise_std = spec.camera.image_noise_std
        self._empty_jpeg = encode_jpeg(self.renderer.background)
        self._last_jpeg: tuple[np.ndarray, bytes] | None = None  # (noise-free image, its JPEG)

    def capture(self, world: TickWorld, labels: bool) -> Capture:
        frame = self.renderer.render(world.poses, world.corners_w, labels=labels)
        if not frame.rois and self.noise_std <= 0:
            data = self._empty_jpeg  # nothing moving in view: the cached static frame
        elif self.noise_std <= 0:
            # The renderer hands a repeated view back as the very same array: encode it once.
            if self._last_jpeg is None or self._last_jpeg[0] is not frame.rgb:
                self._last_jpeg = (frame.rgb, encode_jpeg(frame.rgb))
            data = self._last_jpeg[1]
        else:
            rgb = add_noise(frame.rgb, self.noise_std, sensor_rng(world.seed, self.spec.id, world.tick))
            frame = CameraFrame(rgb, frame.visible_px, frame.visible_boxes, frame.rois)
            data = encode_jpeg(rgb)
        msg = CompressedImage(frame_id=self.spec.id, format="jpeg", data=data)
        msg.timestamp.FromNanoseconds(world.stamp_ns)
        return Capture(self.spec, world.tick, world.stamp_ns, frame, msg)


class LidarSensor:
    def __init__(self, scene: Scene, spec: SensorSpec, static: StaticWorld, vehicles: VehicleWorld) -> None:
        self.spec = spec
        self.simulator = LidarSimulator(scene, spec.id, static, vehicles, spec.lidar)

    def capture(self, world: TickWorld, labels: bool) -> Capture:
        scan = self.simulator.scan(world.poses, sensor_rng(world.seed, self.spec.id, world.tick))
        msg = to_point_cloud(scan, self.spec.id, world.stamp_ns)
        return Capture(self.spec, world.tick, world.stamp_ns, scan, msg)


class RadarSensor:
    def __init__(self, scene: Scene, spec: SensorSpec, static: StaticWorld, vehicles: VehicleWorld) -> None:
        self.spec = spec
        self.simulator = RadarSimulator(scene, spec.id, static, vehicles, spec.radar)

    def capture(self, world: TickWorld, labels: bool) -> Capture:
        targets = self.simulator.scan(world.states, sensor_rng(world.seed, self.spec.id, world.tick))
        return Capture(self.spec, world.tick, world.stamp_ns, targets, to_radar_scan(targets, self.spec.id))


def build_sensor(
    scene: Scene, spec: SensorSpec, static: StaticWorld, vehicles: VehicleWorld, lighting: Lighting
) -> Sensor:
    """The sensor model of `spec`'s kind (`lighting` applies to cameras)."""
    if spec.kind == "camera":
        return CameraSensor(scene, spec, static, vehicles, lighting)
    if spec.kind == "lidar":
        return LidarSensor(scene, spec, static, vehicles)
    return RadarSensor(scene, spec, static, vehicles)


class SensorRig:
    """The sensors `specs` of `scene` over their own PyBullet worlds (static scene + vehicles, built
    with `world`, default the defaults, at the scene's scale).

    Use as a context manager (or call close()) to release the PyBullet clients."""

    def __init__(
        self,
        scene: Scene,
        specs: list[SensorSpec],
        lighting: Lighting | None = None,
        world: WorldSettings | None = None,
    ) -> None:
        self.scene = scene
        self.specs = list(specs)
        self.static = StaticWorld(scene, world)
        self.vehicles = VehicleWorld(scene, settings=self.static.settings)
        light = lighting or Lighting()
        try:
            self.sensors: dict[str, Sensor] = {
                spec.id: build_sensor(scene, spec, self.static, self.vehicles, light) for spec in self.specs
            }
        except BaseException:
            self.close()
            raise

    def firing(self, tick: int, tick_hz: float, every_n: int = 1) -> list[SensorSpec]:
        """The sensors that capture on `tick` when every `every_n`-th frame is wanted (cadence.py)."""
        return [s for s in self.specs if self.scene.captures_on(s, tick, tick_hz, every_n)]

    def tick_world(self, gt: GroundTruth) -> TickWorld:
        return TickWorld.from_ground_truth(gt, self.vehicles.size_m)

    def capture(
        self, gt: GroundTruth, specs: list[SensorSpec] | None = None, labels: bool = False, every_n: int = 1
    ) -> list[Capture]:
        """Captures of `specs` (default: the sensors firing on this tick, every `every_n`-th frame)
        with the world at `gt`."""
        return list(self.captures(gt, specs, labels, every_n))

    def captures(
        self, gt: GroundTruth, specs: list[SensorSpec] | None = None, labels: bool = False, every_n: int = 1
    ) -> Iterator[Capture]:
        """`capture`, one sensor at a time: a live service publishes each frame as soon as it is made,
        so its consumer can start on the first camera while the next one renders."""
        due = self.firing(gt.header.tick, gt.tick_hz, every_n) if specs is None else specs
        if not due:
            return  # most ticks: nothing fires, so no world is built
        world = self.tick_world(gt)
        self.vehicles.update(world.poses)
        for spec in due:
            start_ns = time.time_ns()
            capture = self.sensors[spec.id].capture(world, labels)
            yield replace(capture, start_ns=start_ns, end_ns=time.time_ns())

    def close(self) -> None:
        self.vehicles.close()
        self.static.close()

    def __enter__(self) -> SensorRig:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

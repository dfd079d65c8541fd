"""Sensor service: renders one sensor group (one agent's cameras, lidars or radars) from ground truth.

    python -m services.sensor --group agent1-cameras     # group id = <agent>-<kind>s

Subscribes to `rmmdet/@v1/sim/ground_truth`, keeps the vehicle world at that tick's poses and fires
each sensor on the ticks of its rate (a sensor at rate r fires on the first tick of each 1/r period),
so all sensors of a tick share its stamp; a group that falls behind skips to the newest tick
(latest-wins) and counts the skipped frames. Cameras publish `foxglove.CompressedImage` (JPEG), lidars
`foxglove.PointCloud`, radars `rmmdet.v1.RadarScan`; the rmmdet header carries the ground truth's
stamp and tick. Sensor noise is drawn from a generator seeded by (scenario seed, sensor, tick), so a
rerun with one seed gives identical data whatever the timing. Killing this process stops only its
group (the fault-injection test "a sensor service dies").
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import zenoh
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from google.protobuf.message import Message
from rmmdet.v1.sim_pb2 import GroundTruth

from shared.bus.health import NOMINAL
from shared.bus.node import Node, Publisher, processing_stamp
from shared.scene.model import SensorSpec
from shared.scene.scene import Scene
from shared.service import run_service
from shared.shutdown import GracefulShutdown
from sim.config import DEFAULT_SCENE
from sim.ground_truth import poses_from_ground_truth
from sim.sensors.camera import CameraRenderer, add_noise
from sim.world import StaticWorld, VehiclePose, VehicleWorld

log = logging.getLogger("services.sensor")

JPEG_QUALITY = 85
GT_QUEUE = 8


def sensor_rng(seed: int, sensor_id: str, tick: int) -> np.random.Generator:
    """Noise generator for one sensor frame: depends only on (seed, sensor, tick)."""
    return np.random.default_rng([seed, zlib.crc32(sensor_id.encode()), tick])


def fires(rate_hz: float, tick: int, tick_hz: float) -> bool:
    """True on the first tick of each 1/rate period."""
    return tick == 0 or int(tick * rate_hz / tick_hz) != int((tick - 1) * rate_hz / tick_hz)


class CameraSensor:
    def __init__(self, scene: Scene, spec: SensorSpec, static: StaticWorld, vehicles: VehicleWorld) -> None:
        self.spec = spec
        self.renderer = CameraRenderer(scene, spec.id, static, vehicles)
        assert spec.camera is not None
        self.noise = spec.camera.image_noise_std
        self._empty_jpeg = self._encode(self.renderer.background)

    @staticmethod
    def _encode(rgb: np.ndarray) -> bytes:
        ok, buf = cv2.imencode(
            ".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]
        )
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        return buf.tobytes()

    def frame(self, poses: list[VehiclePose], gt: GroundTruth, stamp_ns: int) -> Message:
        frame = self.renderer.render(poses)
        if not frame.rois and self.noise <= 0:
            data = self._empty_jpeg  # nothing moving in view: the cached static frame
        else:
            rgb = add_noise(frame.rgb, self.noise, sensor_rng(gt.seed, self.spec.id, gt.header.tick))
            data = self._encode(rgb)
        msg = CompressedImage(frame_id=self.spec.id, format="jpeg", data=data)
        msg.timestamp.FromNanoseconds(stamp_ns)
        return msg


STREAM_OF_KIND = {"camera": "camera_image", "lidar": "point_cloud", "radar": "radar_scan"}
# Kinds this service publishes so far. The lidar and radar models (sim/sensors/lidar.py, radar.py) exist
# and are tested but are not wired to the bus yet.
PUBLISHED_KINDS = {"camera"}


def build_sensor(scene: Scene, spec: SensorSpec, static: StaticWorld, vehicles: VehicleWorld) -> CameraSensor:
    return CameraSensor(scene, spec, static, vehicles)


def parse_group(scene: Scene, group: str) -> list[SensorSpec]:
    agent, _, kinds = group.rpartition("-")
    kind = kinds.rstrip("s")
    if agent not in scene.agents or kind not in STREAM_OF_KIND:
        raise SystemExit(f"unknown sensor group {group!r}: expected <agent>-<cameras|lidars|radars>")
    sensors = scene.sensors_of(agent, kind)  # type: ignore[arg-type]
    if not sensors:
        raise SystemExit(f"sensor group {group!r} has no sensors in scene {scene.scene_id}")
    if kind not in PUBLISHED_KINDS:
        raise SystemExit(f"sensor group {group!r}: {kind} sensors are not published by this service yet")
    return sensors


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    scene = Scene.load(args.scene)
    specs = parse_group(scene, args.group)
    agent = specs[0].agent
    static = StaticWorld(scene)
    vehicles = VehicleWorld(scene)
    t0 = time.perf_counter()
    sensors = {spec.id: build_sensor(scene, spec, static, vehicles) for spec in specs}
    log.info("group %s: %d sensors ready in %.2f s", args.group, len(sensors), time.perf_counter() - t0)
    try:
        with Node(conf, service="sensor", instance=args.group, scope=agent, stop=shutdown.event) as node:
            pubs: dict[str, Publisher] = {
                spec.id: node.publisher(
                    STREAM_OF_KIND[spec.kind], agent=agent, sensor=spec.id, source_id=f"{agent}/{spec.id}"
                )
                for spec in specs
            }
            gt_sub = node.subscribe_stream("ground_truth", maxsize=GT_QUEUE)
            stats = {"frames": 0, "skipped": 0, "last_tick": 0}

            def status() -> tuple[int, str]:
                return (
                    NOMINAL,
                    f"{len(sensors)} sensors, {stats['frames']} frames, tick {stats['last_tick']}, "
                    f"{stats['skipped']} ticks skipped",
                )

            node.health.set_status(status)
            last_log = time.monotonic()
            last_tick = -1
            while not shutdown.requested:
                received = gt_sub.recv(timeout=0.1)
                if received is None:
                    continue
                backlog = gt_sub.drain()
                items = [received, *backlog]
                # Latest-wins: render the newest tick on which any sensor fires; count the rest.
                due: tuple[object, list[SensorSpec]] | None = None
                for item in items:
                    gt: GroundTruth = item.message
                    firing = [s for s in specs if fires(s.rate_hz, gt.header.tick, gt.tick_hz)]
                    if firing:
                        if due is not None:
                            stats["skipped"] += 1
                            node.counters.inc("frames/skipped_ticks")
                        due = (item, firing)
                if due is None:
                    continue
                item, firing = due
                gt = item.message
                if gt.header.tick <= last_tick:
                    continue
                last_tick = gt.header.tick
                stats["last_tick"] = last_tick
                poses = poses_from_ground_truth(gt)
                vehicles.update(poses)
                stamp_ns = gt.header.stamp.ToNanoseconds()
                for spec in firing:
                    start_ns = time.time_ns()
                    msg = sensors[spec.id].frame(poses, gt, stamp_ns)
                    stage = processing_stamp(f"sensor/{spec.kind}", start_ns, time.time_ns())
                    pub = pubs[spec.id]
                    header = pub.next_header(derived_from=gt.header, frame_id=spec.id)
                    if hasattr(msg, "header"):
                        msg.header.CopyFrom(header)
                    pub.put(msg, header, stages=[stage])
                    stats["frames"] += 1
                    node.counters.inc(f"frames/{spec.kind}")
                now = time.monotonic()
                if now - last_log >= args.report_interval_s:
                    log.info(
                        "%d frames published, tick %d, %d ticks skipped",
                        stats["frames"],
                        last_tick,
                        stats["skipped"],
                    )
                    last_log = now
    finally:
        vehicles.close()
        static.close()
    return 0


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--group", required=True, help="sensor group: <agent>-<cameras|lidars|radars>")
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE, help="scene YAML")
    parser.add_argument("--report-interval-s", type=float, default=10.0, help="log interval")


def cli(argv: list[str] | None = None) -> int:
    return run_service("sensor", main, description=__doc__ or "", add_args=add_args, argv=argv)


if __name__ == "__main__":
    sys.exit(cli())

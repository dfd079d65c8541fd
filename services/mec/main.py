"""MEC (edge) service: one agent's detection, fusion and tracking.

    python -m services.mec --instance agent1

A shell around `MecCore` (shared/perception/core.py: input health, join, camera cadence, decode,
detect-fuse-track, FULL / DEGRADED status, output message; the studies drive the same core). Here: the
bus. Subscribes to every sensor of the agent (`rmmdet/v1/<agent>/sensor/<kind>/<id>`) into one
latest-wins queue, feeds the core on the clock of record (sim time under a sim), and publishes
`rmmdet.v1.TrackedObjects` on `rmmdet/v1/<agent>/objects` with the frame's stamp. Under a sim it asks
its cameras for just the frames the detector runs on (`capture_demand`, renewed every second); a
sensor service whose presence token vanishes makes its sensors MISSING at once. Each camera's 2D
detections go out on `rmmdet/v1/<agent>/perception/detections_2d/<camera>` only while something
subscribes (the viewer's image annotations).
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import zenoh
from rmmdet.v1.sensors_pb2 import CaptureDemand

from shared.bus import names
from shared.bus.liveliness import source_of_token
from shared.bus.node import Node, Received, processing_stamp
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.bus.streams import SENSOR_STREAM, get_stream, limits, sensor_group_source
from shared.config import load_settings
from shared.devices.site import SiteFile
from shared.logging_setup import ReportTimer
from shared.paths import DEFAULT_SCENE
from shared.perception.config import DEFAULT_MEC_CONFIG, MecSettings
from shared.perception.core import MecCore, MecOutput
from shared.perception.output import detections_2d_message
from shared.scene.cadence import DemandRenewal
from shared.scene.scene import Scene
from shared.service import exit_process, report_interval_s, run_service
from shared.shutdown import GracefulShutdown
from shared.timebase import SimTime

log = logging.getLogger("services.mec")

QUEUE_PER_SENSOR = 4  # latest-wins: a few frames per sensor, oldest dropped
IDLE_WAIT_S = 0.1


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    scene = Scene.load(args.scene)
    if args.site is not None:  # a real site: its sensors' calibration (rmmdet calibrate) over the scene's
        scene = SiteFile.load(args.site).calibrated_scene(scene)
    agent = args.instance
    if agent not in scene.agents:
        raise SystemExit(f"unknown agent {agent!r}: scene has {sorted(scene.agents)}")
    chosen = {"camera": args.camera_detector, "lidar": args.lidar_detector}
    settings = load_settings(MecSettings, args.settings, detectors={k: v for k, v in chosen.items() if v})
    t0 = time.perf_counter()
    try:
        core = MecCore(scene, agent, settings, sensor_ids=args.sensors.split(",") if args.sensors else None)
    except ValueError as err:
        raise SystemExit(f"mec {agent}: {err}") from None
    log.info(
        "agent %s: sensors %s, pipeline ready in %.2f s", agent, sorted(core.kinds), time.perf_counter() - t0
    )
    with Node(conf, service=names.MEC, instance=agent, scope=agent, stop=shutdown.event) as node:
        objects_pub = node.publisher("objects", agent=agent, source_id=f"{agent}/mec")
        queue = BoundedQueue[Received](
            QUEUE_PER_SENSOR * len(core.kinds), OverflowPolicy.DROP_OLDEST, node.counters
        )
        # No expected rate on the bus-level monitors: a missing sensor makes this MEC DEGRADED (its
        # status below names it), not CRITICAL; the rates are still reported per input.
        # Input health is judged on the clock of record (sim time when a sim runs): a slow host slows
        # the sim, not the verdict. The core starts afresh when the sim clock is first heard. Frames
        # stamped ahead of that clock are refused (one must not make the join drop what follows).
        sim_time = SimTime()
        node.follow_sim_time(sim_time)
        for sensor_id, kind in core.kinds.items():
            node.subscribe_stream(
                SENSOR_STREAM[kind],
                agent=agent,
                sensor=sensor_id,
                queue=queue,
                clock_s=sim_time.now_s,
                max_future_s=limits().max_clock_skew_s,
            )
        core.reset(sim_time.now_s())
        demand_pub = node.publisher("capture_demand", agent=agent, kind="camera") if core.camera_ids else None
        renewal = DemandRenewal()
        # A sensor service that leaves the bus (killed, crashed) takes its sensors with it at once: its
        # presence token vanishes long before 3 periods (3 s) of a camera asked for every 10th frame.
        groups: dict[str, list[str]] = {}
        for sensor_id, kind in core.kinds.items():
            groups.setdefault(sensor_group_source(agent, kind), []).append(sensor_id)
        presence = node.presence(get_stream("alive").pattern(scope=agent, service=names.SENSOR))
        following = sim_time.following
        node.health.set_status(lambda: core.health(sim_time.now_s()))
        report = ReportTimer(report_interval_s(args, settings.report_interval_s))
        while not shutdown.requested:
            node.health.beat()
            # The join waits on the clock of record: a sim held back by a slow consumer holds the
            # wait too, so an input late only because the host is busy is not dropped.
            received = queue.get(timeout=core.wait_s(sim_time.now_s(), sim_time.speed, IDLE_WAIT_S))
            items = ([received] if received is not None else []) + queue.drain()
            if sim_time.following != following:
                following = sim_time.following
                core.reset(sim_time.now_s())  # pending frames were timed on the other clock
            clock_s = sim_time.now_s()
            for key, alive in presence.changes():
                for sensor_id in [] if alive else groups.get(source_of_token(key) or "", []):
                    core.mark_gone(sensor_id)
                    log.warning("%s: its sensor service left the bus", sensor_id)
            core.tick_hz = sim_time.tick_hz
            every_n, changed = core.cadence(clock_s)
            if changed:
                log.info("cameras: every %d frame(s)", every_n)
            # Under a sim the cameras are asked for just the frames the detector runs on; they fall
            # back to every frame if this MEC is gone (the demand lapses).
            if demand_pub is not None and core.tick_hz is not None and renewal.due(time.monotonic(), changed):
                reason = "lidar live" if every_n > 1 else "no lidar"
                demand = CaptureDemand(every_n=every_n, valid_for_s=renewal.valid_for_s, reason=reason)
                demand_pub.put(demand, stamp_ns=sim_time.now_ns())  # on the clock of record, as judged
            for item in items:
                sensor_id, stamp_ns = item.key.rsplit("/", 1)[-1], item.header.stamp.ToNanoseconds()
                arrival_ns = sim_time.now_ns(item.received_wall_ns)
                rejected = core.receive(
                    sensor_id,
                    stamp_ns,
                    item.header.tick,
                    item.message,
                    clock_s,
                    arrival_ns,
                    item.header.epoch,
                )
                if rejected:
                    node.counters.inc(f"rejected/{rejected}")
            out = core.step(clock_s)
            if out is None:
                continue
            header = objects_pub.next_header(
                stamp_ns=out.frame.stamp_ns, tick=out.frame.tick, frame_id="world"
            )
            objects_pub.put(
                out.message, header, stages=[processing_stamp("mec/process", out.started_ns, time.time_ns())]
            )
            publish_detections_2d(node, agent, out)
            node.counters.publish(core.counts())  # stale / late frames per sensor, skipped, coasted, ...
            if report.due():
                log.info(
                    "%d frames published, status %s, %d tracks, counters %s",
                    core.counters["frames/published"],
                    out.status.value,
                    len(out.result.tracks),
                    dict(core.counts()),
                )
    return 0


def publish_detections_2d(node: Node, agent: str, out: MecOutput) -> None:
    """Each camera's 2D detections of this frame, stamped as its image, for the live view's image
    annotations: only while something subscribes (a viewer watching that camera), so they cost
    nothing otherwise."""
    for camera_id, boxes in out.result.camera_boxes.items():
        pub = node.publisher("detections_2d", agent=agent, sensor=camera_id)
        image, sample = out.inputs.images.get(camera_id), out.frame.samples.get(camera_id)
        if image is None or sample is None or not pub.has_subscribers():
            continue
        height, width = image.shape[:2]
        pub.put(
            detections_2d_message(camera_id, boxes, width, height),
            stamp_ns=sample.stamp_ns,
            tick=sample.tick,
            epoch=sample.epoch,
            frame_id=camera_id,
        )
        node.counters.inc("published/detections_2d")


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE, help="scene YAML")
    parser.add_argument("--settings", type=Path, default=DEFAULT_MEC_CONFIG, help="MEC settings YAML")
    parser.add_argument("--site", type=Path, help="site file: its calibration replaces the scene's")
    parser.add_argument(
        "--sensors", help="comma-separated subset of the agent's sensors to fuse (default all)"
    )
    parser.add_argument("--camera-detector", help="override detectors.camera (onnx | oracle | CARD.yaml)")
    parser.add_argument(
        "--lidar-detector", help="override detectors.lidar (pointpillars | cluster | oracle | CARD.yaml)"
    )


def cli(argv: list[str] | None = None) -> int:
    return run_service("mec", main, description=__doc__ or "", add_args=add_args, argv=argv)


if __name__ == "__main__":
    exit_process(cli())

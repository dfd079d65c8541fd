"""Sensor service: renders one sensor group (one agent's cameras, lidars or radars) from ground truth.

    python -m services.sensor --group agent1-cameras     # group id = <agent>-<kind>s

Subscribes to `rmmdet/v1/sim/ground_truth`, keeps the vehicle world at that tick's poses and fires
each sensor on the ticks of its rate (a sensor at rate r fires on the first tick of each 1/r period,
its agent's `sensor_phase_ticks` later), so all sensors of a tick share its stamp; each capture is
published as soon as it is made; a group that falls behind skips to the newest tick
(latest-wins) and counts the skipped frames. Cameras publish `foxglove.CompressedImage` (JPEG), lidars
`foxglove.PointCloud`, radars `rmmdet.v1.RadarScan`; the rmmdet header carries the ground truth's
stamp and tick. A consumer may ask for fewer frames (`rmmdet/v1/<agent>/capture_demand/<kind>`, e.g.
the MEC wants every 10th camera frame while a lidar covers its area): the group then captures only the
frames `Scene.captures_on` names (staggered: one camera per frame, not all on one), for as long as
the demand is renewed. Sensor noise is drawn from a generator seeded by (scenario seed, sensor,
tick), so a rerun with one seed gives identical data whatever the timing. Killing this process stops
only its group (the fault-injection test "a sensor service dies").

    python -m services.sensor --group agent1-lidars --wire deploy/devices/sand_table_wire.yaml

With `--wire SITE` the group is its devices instead: each capture goes out in the wire format of the
device the site file names (sim/emulators/group.py) and nothing is published on the bus; the device
service (services/device) reads the wire and publishes. The process is then the `emulator` service
(presence `<agent>/emulator/<group>`), so the device service alone holds the group's sensor presence.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import zenoh
from rmmdet.v1.sim_pb2 import GroundTruth

from shared.bus import names
from shared.bus.health import NOMINAL
from shared.bus.node import Node, Publisher, Received, processing_stamp
from shared.bus.ordering import OrderGate, reset_after_ticks
from shared.bus.streams import SENSOR_STREAM, limits
from shared.devices.site import SiteFile
from shared.logging_setup import ReportTimer
from shared.paths import DEFAULT_SCENE
from shared.scene.cadence import CaptureDemands
from shared.scene.model import SensorSpec
from shared.scene.scene import Scene
from shared.service import exit_process, report_interval_s, run_service
from shared.shutdown import GracefulShutdown
from shared.timebase import SimTime
from sim.config import DEFAULT_SIM_CONFIG, load_sim_settings
from sim.emulators.group import WireGroup
from sim.sensors.rig import SensorRig

log = logging.getLogger("services.sensor")

GT_QUEUE = 8
DEMAND_QUEUE = 16  # capture demands: one per consumer per second


def newest_due(
    items: list[Received], scene: Scene, specs: list[SensorSpec], every_n: int = 1
) -> tuple[Received | None, int]:
    """Latest-wins: the newest ground truth on which any of `specs` captures (every `every_n`-th
    frame), and how many earlier due ticks it supersedes (skipped frames)."""
    due: Received | None = None
    skipped = 0
    for item in items:
        gt: GroundTruth = item.message
        if any(scene.captures_on(s, gt.header.tick, gt.tick_hz, every_n) for s in specs):
            if due is not None:
                skipped += 1
            due = item
    return due, skipped


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    scene = Scene.load(args.scene)
    site = SiteFile.load(args.wire) if args.wire is not None else None
    if site is not None:
        scene = site.simulated_scene(scene)  # the site's lidars fire their devices' rays
    specs = scene.group_sensors(args.group, args.only)
    agent, kind = specs[0].agent, specs[0].kind
    wire: WireGroup | None = None
    if site is not None:
        try:
            wire = WireGroup(site, specs)
        except (ValueError, KeyError, OSError) as exc:
            raise SystemExit(f"--wire {args.wire}: {exc}") from None
    try:
        t0 = time.perf_counter()
        service = names.SENSOR if wire is None else names.EMULATOR
        with (
            SensorRig(scene, specs, world=load_sim_settings(args.settings).world) as rig,
            Node(conf, service=service, instance=args.group, scope=agent, stop=shutdown.event) as node,
        ):
            log.info("group %s: %d sensors ready in %.2f s", args.group, len(specs), time.perf_counter() - t0)
            pubs: dict[str, Publisher] = (
                {
                    spec.id: node.publisher(
                        SENSOR_STREAM[spec.kind], agent=agent, sensor=spec.id, source_id=f"{agent}/{spec.id}"
                    )
                    for spec in specs
                }
                if wire is None
                else {}
            )
            # Ground truth ahead of the sim's own clock is refused, and the tick order restarts with a
            # new sim run (epoch) or after a bogus tick (shared/bus/ordering.py): nothing latches it.
            sim_time = SimTime()
            node.follow_sim_time(sim_time)
            bus_limits = limits()
            gt_sub = node.subscribe_stream(
                "ground_truth",
                maxsize=GT_QUEUE,
                clock_s=sim_time.now_s,
                max_future_s=bus_limits.max_clock_skew_s,
            )
            ticks: OrderGate | None = None
            demand_sub = node.subscribe_stream(
                "capture_demand",
                agent=agent,
                kind=kind,
                maxsize=DEMAND_QUEUE,
                clock_s=sim_time.now_s,
                max_future_s=bus_limits.max_clock_skew_s,
            )
            demands = CaptureDemands()
            stats = {"frames": 0, "skipped": 0, "last_tick": -1, "every_n": 1}

            def status() -> tuple[int, str]:
                return (
                    NOMINAL,
                    f"{len(specs)} sensors, {stats['frames']} frames, tick {stats['last_tick']}, "
                    f"{stats['skipped']} ticks skipped, every {stats['every_n']} frame(s)"
                    + (f"; on the wire: {wire.status()}" if wire is not None else ""),
                )

            node.health.set_status(status)
            report = ReportTimer(report_interval_s(args))
            while not shutdown.requested:
                node.health.beat()
                received = gt_sub.recv(timeout=0.1)
                if received is None:
                    continue
                now = time.monotonic()
                node.counters.inc("rejected/capture_demand", demands.take(demand_sub.drain(), now))
                every_n = demands.every_n(now)
                if every_n != stats["every_n"]:
                    log.info("capturing every %d frame(s) (was %d)", every_n, stats["every_n"])
                    stats["every_n"] = every_n
                due, skipped = newest_due([received, *gt_sub.drain()], scene, specs, every_n)
                stats["skipped"] += skipped
                node.counters.inc("frames/skipped_ticks", skipped)
                if due is None:
                    continue
                gt: GroundTruth = due.message
                if ticks is None:
                    ticks = OrderGate(reset_after_ticks(gt.tick_hz))
                if not ticks.admit(gt.header.epoch, gt.header.tick):
                    continue
                stats["last_tick"] = gt.header.tick
                for capture in rig.captures(gt, every_n=every_n):  # each published as soon as made
                    stats["frames"] += 1
                    if wire is not None:
                        wire.send(capture, due.received_wall_ns)
                        node.counters.inc(f"frames/{capture.spec.kind}")
                        continue
                    stage = processing_stamp(f"sensor/{capture.spec.kind}", capture.start_ns, capture.end_ns)
                    pub = pubs[capture.spec.id]
                    header = pub.next_header(derived_from=gt.header, frame_id=capture.spec.id)
                    if hasattr(capture.message, "header"):
                        capture.message.header.CopyFrom(header)
                    pub.put(capture.message, header, stages=[stage])
                    node.counters.inc(f"frames/{capture.spec.kind}")
                if report.due():
                    log.info(
                        "%d frames published, tick %d, %d ticks skipped, tick order restarted %d times",
                        stats["frames"],
                        stats["last_tick"],
                        stats["skipped"],
                        ticks.restarts if ticks is not None else 0,
                    )
    finally:
        if wire is not None:
            wire.close()
    return 0


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--group", required=True, help="sensor group: <agent>-<cameras|lidars|radars>")
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE, help="scene YAML")
    parser.add_argument(
        "--settings",
        type=Path,
        default=DEFAULT_SIM_CONFIG,
        help="the sim's settings (its `world` section: how the sensors render, as in lock-step runs)",
    )
    parser.add_argument("--only", help="comma-separated subset of the group's sensors (tests)")
    parser.add_argument("--wire", type=Path, help="site file: emulate the group's devices on the wire")


def cli(argv: list[str] | None = None) -> int:
    return run_service("sensor", main, description=__doc__ or "", add_args=add_args, argv=argv)


if __name__ == "__main__":
    exit_process(cli())

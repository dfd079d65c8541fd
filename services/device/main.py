"""Device service: one sensor group's real (or emulated) devices onto the bus, as the simulator's group.

    python -m services.device --group agent1-lidars --site deploy/devices/sand_table_wire.yaml

Every sensor of the group must be in the site file (shared/devices/site.py), which says what device
it is and where it is reached: Robosense lidars on their MSOP / DIFOP UDP ports, ARS 408 radars on a
CAN bus, cameras on a stream URL. Each device is read on its own thread (shared/devices/sources.py)
and each frame published on the keys, with the frame ids, header fields and message types the sim's
sensor service uses, under the same presence (`<agent>/sensor/<agent>-<kind>s`): a MEC cannot tell
the two apart. Stamps follow the site file's clock per sensor; under a sim clock each frame also gets
its capture tick (shared/devices/stamping.py). Cameras honour capture demands as the sim's cameras do:
a frame is published only if its camera is due at the demanded cadence (by tick under a sim, else
every n-th frame).

Health: NOMINAL while every device delivers; DEGRADED naming each device that does not (no DIFOP yet,
radar not configured, bus-off, stream down, silent), with per-device counters of what was refused.
A device that fails is reopened with backoff; the service itself never needs a restart for it.
"""

from __future__ import annotations

import argparse
import logging
import queue
import time
from pathlib import Path

import zenoh

from shared.bus import names
from shared.bus.health import DEGRADED, NOMINAL
from shared.bus.node import Node, Publisher, processing_stamp
from shared.bus.streams import SENSOR_STREAM, limits
from shared.devices.site import SiteFile
from shared.devices.sources import Output, counters_by_reason, source_for
from shared.devices.stamping import Stamper, frame_wanted
from shared.logging_setup import ReportTimer
from shared.perception.inputs import InputState, SensorMonitor
from shared.scene.cadence import CaptureDemands
from shared.scene.scene import Scene
from shared.service import exit_process, report_interval_s, run_service
from shared.shutdown import GracefulShutdown
from shared.timebase import SimTime

log = logging.getLogger("services.device")

OUTPUT_QUEUE = 64
SILENT_PERIODS = 3.0  # a sensor with no frame for this many of its periods is reported silent
DEMAND_QUEUE = 16
COUNTERS_EVERY_S = 1.0  # the devices' own counters (by reason) taken into the health report this often


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    site = SiteFile.load(args.site)
    scene = Scene.load(site.scene)
    site.check_against({s.id: s.kind for s in scene.spec.sensors})
    specs = scene.group_sensors(args.group, args.only)
    agent, kind = specs[0].agent, specs[0].kind
    outputs: queue.Queue[Output] = queue.Queue(maxsize=OUTPUT_QUEUE)
    dropped = {"queue_full": 0}

    def emit(output: Output) -> None:
        try:
            outputs.put_nowait(output)
        except queue.Full:  # the publisher fell behind: the newest frames matter, count the loss
            dropped["queue_full"] += 1

    with Node(conf, service=names.SENSOR, instance=args.group, scope=agent, stop=shutdown.event) as node:
        sim_time = SimTime()
        node.follow_sim_time(sim_time)
        sources = {spec.id: source_for(site, spec, emit) for spec in specs}
        by_id = {spec.id: spec for spec in specs}
        stampers = {spec.id: Stamper(scene, spec, sim_time, site.device(spec.id).latency_s) for spec in specs}
        pubs: dict[str, Publisher] = {
            spec.id: node.publisher(
                SENSOR_STREAM[kind], agent=agent, sensor=spec.id, source_id=f"{agent}/{spec.id}"
            )
            for spec in specs
        }
        demand_sub = (
            node.subscribe_stream(
                "capture_demand",
                agent=agent,
                kind=kind,
                maxsize=DEMAND_QUEUE,
                clock_s=sim_time.now_s,
                max_future_s=limits().max_clock_skew_s,
            )
            if kind == "camera"
            else None
        )
        demands = CaptureDemands()
        published = dict.fromkeys(sources, 0)
        seen = dict.fromkeys(sources, 0)
        # Silence on the clock of record (a held sim holds it too), at the cadence asked of each sensor.
        monitor = SensorMonitor({s.id: s.rate_hz for s in specs}, SILENT_PERIODS, 0.0, sim_time.now_s())
        cadence = {"every_n": 1}

        def status() -> tuple[int, str]:
            now_s = sim_time.now_s()
            problems = [f"{sid}: {text}" for sid, src in sources.items() if (text := src.status())]
            problems += [
                f"{r.sensor_id}: nothing for {r.age_s:.1f} s"
                if r.age_s >= 0
                else f"{r.sensor_id}: nothing yet"
                for r in monitor.report(now_s)
                if r.state is not InputState.OK and not sources[r.sensor_id].status()
            ]
            counts = ", ".join(f"{sid} {published[sid]}" for sid in sources)
            if problems:
                return DEGRADED, "; ".join(problems) + f" (frames: {counts})"
            return NOMINAL, f"{len(sources)} devices, frames: {counts}"

        node.health.set_status(status)

        frame_errors = {"n": 0}

        def publish(out: Output, now: float) -> None:
            """Stamp, demand-check and publish one device output."""
            start_ns = time.time_ns()
            seen[out.sensor_id] += 1
            spec = by_id[out.sensor_id]
            stamp = stampers[out.sensor_id].stamp(out.stamp_ns, out.on_wall_clock, out.cycle)
            every_n = demands.every_n(now)
            if kind == "camera" and every_n != cadence["every_n"]:
                cadence["every_n"] = every_n
                for sid in sources:
                    monitor.set_rate(sid, by_id[sid].rate_hz / every_n, sim_time.now_s())
            if kind == "camera" and not frame_wanted(
                scene, spec, stamp.tick, sim_time, every_n, seen[out.sensor_id]
            ):
                node.counters.inc("frames/not_demanded")
                return
            message = out.message
            if hasattr(message, "timestamp"):
                message.timestamp.FromNanoseconds(stamp.stamp_ns)
            pub = pubs[out.sensor_id]
            header = pub.next_header(
                stamp_ns=stamp.stamp_ns, tick=stamp.tick, epoch=stamp.epoch, frame_id=out.sensor_id
            )
            if hasattr(message, "header"):
                message.header.CopyFrom(header)
            pub.put(message, header, stages=[processing_stamp(f"device/{kind}", start_ns, time.time_ns())])
            published[out.sensor_id] += 1
            monitor.accept(out.sensor_id, stamp.stamp_ns, sim_time.now_s(), stamp.stamp_ns)
            node.counters.inc(f"frames/{kind}")

        for source in sources.values():
            source.start()
        log.info("group %s: %d devices from site %s", args.group, len(sources), site.site_id)
        report, counters_due = ReportTimer(report_interval_s(args)), ReportTimer(COUNTERS_EVERY_S)
        try:
            while not shutdown.requested:
                node.health.beat()
                now = time.monotonic()
                if counters_due.due():  # `rmmdet health` shows them by reason
                    node.counters.publish(
                        counters_by_reason(sources) | {"dropped/queue_full": dropped["queue_full"]}
                    )
                if demand_sub is not None:
                    node.counters.inc("rejected/capture_demand", demands.take(demand_sub.drain(), now))
                if report.due():
                    for sid, src in sources.items():
                        low_ms, median_ms, high_ms = stampers[sid].snap_summary_ms()
                        log.info(
                            "%s: %d frames published, %d read, stamp - capture %.1f / %.1f / %.1f ms "
                            "(min / median / max), %d given their predecessor's capture%s, %s",
                            sid, published[sid], seen[sid], low_ms, median_ms, high_ms,
                            stampers[sid].repeated, stampers[sid].cycles_text(), src.counters_snapshot(),
                        )  # fmt: skip
                    if dropped["queue_full"]:
                        log.warning("%d frames dropped: publishing fell behind", dropped["queue_full"])
                try:
                    out = outputs.get(timeout=0.1)
                except queue.Empty:
                    continue
                try:
                    publish(out, now)
                except Exception:  # one frame's fault (a field no message holds) never ends the group
                    frame_errors["n"] += 1
                    node.counters.inc("errors/frame")
                    if frame_errors["n"] == 1:  # the first with its trace; the rest counted
                        log.exception("%s: a frame could not be published; later ones counted", out.sensor_id)
        finally:
            for source in sources.values():
                source.close()
    return 0


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--group", required=True, help="sensor group: <agent>-<cameras|lidars|radars>")
    parser.add_argument("--site", type=Path, required=True, help="site file (deploy/devices/*.yaml)")
    parser.add_argument("--only", help="comma-separated subset of the group's sensors (tests)")


def cli(argv: list[str] | None = None) -> int:
    return run_service("device", main, description=__doc__ or "", add_args=add_args, argv=argv)


if __name__ == "__main__":
    exit_process(cli())

"""Sim service: drives the sand-table traffic and publishes ground truth, the sim clock and calibration.

    python -m services.sim [--settings deploy/sim/sim.yaml] [--speed 1.0] [--vehicles 10] [--seed 0]

Ticks run at 60 Hz of sim time. On every tick on which a scene sensor fires (each agent at 10 Hz on its
own phase: 30 Hz) it publishes `rmmdet/v1/sim/ground_truth`, stamped with the sim time (start wall
time + sim seconds: the clock of record, shared/timebase.py); the sensor services render from it. It
also publishes the SimClock (sim time, target speed, measured real-time factor) and each agent's
CalibrationSet at low rate. The wall-clock schedule is sim/realtime.py; pacing (a tick held back while
a consumer lags, so a slow host slows the whole loop together) is sim/pacing.py. With route policy
`plan` the vehicles are the coordinator's clients (services/sim/plans.py). `--speed 0`: as fast as
possible.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import time
from pathlib import Path

import zenoh

from services.sim.plans import PlanCheck, PlanClient, missing_vehicle_configs, open_vehicle_nodes
from services.sim.progress import SimProgress
from shared.bus import names
from shared.bus.liveliness import source_of_token
from shared.bus.node import Node, Received, processing_stamp
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.bus.streams import get_stream, producer_of
from shared.logging_setup import ReportTimer
from shared.scene.calibration import calibration_set
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.security.plan_signing import PlanVerifier
from shared.service import exit_process, report_interval_s, run_service
from shared.shutdown import GracefulShutdown
from shared.timebase import tick_stamp_ns
from sim.config import DEFAULT_SIM_CONFIG, load_sim_settings
from sim.ground_truth import ground_truth_message, sim_clock_message
from sim.pacing import Pacer
from sim.realtime import Every, RealTimeSchedule
from sim.traffic import TrafficSim

log = logging.getLogger("services.sim")

SCOPE = "sim"
RTF_WINDOW_S = 2.0  # real-time factor measured over this wall window
LATE_TOLERANCE_S = 0.25  # behind schedule by more than this: the schedule moves on (no sprint)
HOLD_POLL_S = 0.002  # while held: how often the consumers' progress is looked at
PACING_QUEUE = 256  # consumer outputs between two looks (18 sensors + 3 MECs at 10 Hz)


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    given = {k: v for k in ("speed", "seed", "scene") if (v := getattr(args, k)) is not None}
    settings = load_sim_settings(args.settings, args.vehicles, **given)
    scene = Scene.load(settings.scene)
    traffic = TrafficSim(
        scene, RoadNetwork(scene), settings.traffic, settings.seed, settings.tick_hz, keep_trips=False
    )
    if args.vehicle_configs is not None:
        missing = missing_vehicle_configs(args.vehicle_configs, traffic)
        if missing:  # such a vehicle could not ask for a plan: the sim's identity holds no vehicle's rights
            log.error(
                "%s: no identity config for vehicles %s (the layout lists the vehicles the sim drives)",
                args.vehicle_configs,
                missing,
            )
            return 2
    collision_every = max(1, round(settings.tick_hz / settings.collision_check_hz))
    pacer = Pacer(settings.pacing.max_lag_s, settings.pacing.consumer_timeout_s)
    pacing = settings.speed > 0 and settings.pacing.enabled
    with (
        Node(conf, service=names.SIM, instance=args.instance, scope=SCOPE, stop=shutdown.event) as node,
        contextlib.ExitStack() as stack,
    ):
        gt_pub, clock_pub = node.publisher("ground_truth"), node.publisher("sim_clock")
        # The scene is fixed: each agent's calibration is made once.
        calibs = {node.publisher("calibration", agent=a): calibration_set(scene, a) for a in scene.agents}
        outputs = BoundedQueue[Received](
            PACING_QUEUE, OverflowPolicy.DROP_OLDEST, node.counters, "dropped/pacing"
        )
        for stream in settings.pacing.streams if pacing else []:
            node.subscribe_stream(stream, queue=outputs)
        # Not held: a consumer forgotten early (e.g. in a router blip) holds again at its next output.
        presence = node.presence(get_stream("alive").pattern(), hold_leaves=False) if pacing else None
        start_wall_ns = time.time_ns()  # wall time of sim time 0: stamps are start + sim time
        plans = None
        if settings.traffic.route_policy == "plan":
            check = PlanCheck(
                PlanVerifier.watching(settings.plan_key_source()),
                settings.plan_max_ttl_s,
                node.counters,
                run_start_ns=start_wall_ns,
            )
            vehicle_nodes = (
                open_vehicle_nodes(args.vehicle_configs, traffic, node, shutdown, stack)
                if args.vehicle_configs is not None
                else None
            )
            plans = PlanClient(node, traffic, settings.plan_request_timeout_s, check, vehicle_nodes)
        schedule = RealTimeSchedule(settings.speed, LATE_TOLERANCE_S, RTF_WINDOW_S)

        def take_progress() -> None:
            now = time.monotonic()
            for item in outputs.drain():
                pacer.on_progress(producer_of(item.key), item.header.stamp.ToNanoseconds(), now)
            for key, alive in presence.changes() if presence is not None else []:
                source = source_of_token(key)
                if not alive and source is not None:  # a consumer that left holds nothing
                    pacer.forget(source)

        progress = SimProgress(traffic, schedule, pacer, settings.speed, plans)
        node.health.set_status(progress.status)
        # This run's epoch (Header.epoch): receivers restart their tick order when it changes.
        epoch = start_wall_ns
        clock_due, calib_due = (
            Every(1 / settings.clock_publish_hz),
            Every(1 / settings.calibration_publish_hz),
        )
        report = ReportTimer(report_interval_s(args))
        log.info(
            "sim up: scene %s, %d vehicles, seed %d, %g Hz ticks, speed %s, route policy %s, pacing %s",
            scene.scene_id,
            len(traffic.vehicles),
            settings.seed,
            settings.tick_hz,
            settings.speed or "max",
            settings.traffic.route_policy,
            f"to {settings.pacing.streams} within {settings.pacing.max_lag_s} s" if pacing else "off",
        )
        while not shutdown.requested:
            node.health.beat()
            if plans is not None:  # replies and pushes that arrived, then this tick's requests
                plans.tick(tick_stamp_ns(epoch, traffic.tick, settings.tick_hz))
            t0 = time.time_ns()
            traffic.step()
            stamp_ns = tick_stamp_ns(epoch, traffic.tick, settings.tick_hz)
            sensor_tick = bool(scene.agents_capturing_on(traffic.tick, settings.tick_hz))
            wait_s = schedule.delay_s(traffic.time_s)  # publish a tick at its stamp, not before
            if wait_s > 0 and shutdown.wait(wait_s):
                break
            if sensor_tick and pacing:
                schedule.hold(pacer.hold(stamp_ns, take_progress, shutdown.wait, HOLD_POLL_S))
            if sensor_tick:  # the sensors fire only on these ticks: nobody else needs ground truth
                msg = ground_truth_message(traffic, scene, settings.seed, settings.tick_hz)
                msg.header.CopyFrom(
                    gt_pub.next_header(stamp_ns=stamp_ns, tick=traffic.tick, epoch=epoch, frame_id="world")
                )
                gt_pub.put(msg, msg.header, stages=[processing_stamp("sim/step", t0, time.time_ns())])
                node.counters.inc("published/ground_truth")
            if traffic.tick % collision_every == 0:
                for pair in traffic.overlapping_pairs():
                    node.counters.inc("traffic/overlaps")
                    log.warning("vehicles overlap: %s", pair)
            if clock_due.due(traffic.time_s):
                rtf = schedule.measure(traffic.time_s)
                clock = sim_clock_message(traffic, stamp_ns, rtf, settings.speed, pacer.paced_by)
                clock_pub.put(clock, stamp_ns=stamp_ns, tick=traffic.tick, epoch=epoch, frame_id="world")
            for pub, calib in calibs.items() if calib_due.due(traffic.time_s) else []:
                pub.put(calib, stamp_ns=stamp_ns, tick=traffic.tick, epoch=epoch)
            if report.due():
                log.info("%s", progress.report())
        if plans is not None:
            plans.close()
    return 0


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--settings", type=Path, default=DEFAULT_SIM_CONFIG, help="sim settings YAML")
    parser.add_argument("--scene", type=Path, default=None, help="scene YAML (default: the settings' scene)")
    parser.add_argument("--speed", type=float, default=None, help="sim seconds per wall second (0 = max)")
    parser.add_argument("--seed", type=int, default=None, help="scenario seed")
    parser.add_argument("--vehicles", type=int, default=None, help="number of vehicles")
    parser.add_argument(
        "--vehicle-configs",
        type=Path,
        default=None,
        help="directory of vehicle-<id>.json Zenoh configs: each vehicle on its own identity (multi-site)",
    )


def cli(argv: list[str] | None = None) -> int:
    return run_service("sim", main, description=__doc__ or "", add_args=add_args, argv=argv)


if __name__ == "__main__":
    exit_process(cli())

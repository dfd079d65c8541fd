"""Sim service: drives the sand-table traffic and publishes ground truth, the sim clock and calibration.

    python -m services.sim [--settings deploy/sim/sim.yaml] [--speed 1.0] [--vehicles 10] [--seed 0]

Every tick (default 60 Hz of simulated time) it publishes `rmmdet/@v1/sim/ground_truth` stamped with
the sim time (start wall time + tick / tick_hz, so latencies measured downstream are real at 1x);
sensor services render from it, so all sensors of one tick share its stamp. It also publishes the
SimClock (with the measured real-time factor) and each agent's CalibrationSet at low rate. With route
policy `plan` the vehicles are the coordinator's clients (services/sim/plans.py): they ask for plans
over the route RPC, follow the plans they get (replies and pushes) and acknowledge each one; requests
never block the tick loop. `--speed 0` runs as fast as possible (no wall-clock pacing).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import zenoh
from rmmdet.v1.sim_pb2 import SimClock

from services.sim.plans import PlanClient
from shared.bus.health import DEGRADED, NOMINAL
from shared.bus.node import Node, processing_stamp
from shared.scene.calibration import calibration_set
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.service import run_service
from shared.shutdown import GracefulShutdown
from sim.config import DEFAULT_SIM_CONFIG, SimSettings, load_sim_settings
from sim.ground_truth import ground_truth_message
from sim.traffic import TrafficSim

log = logging.getLogger("services.sim")

SCOPE = "sim"
RTF_WINDOW_S = 2.0  # real-time factor measured over this wall window
LATE_TOLERANCE_S = 0.25  # behind schedule by more than this: report DEGRADED
NS = 1_000_000_000


def load(args: argparse.Namespace) -> SimSettings:
    overrides: dict[str, object] = {}
    if args.speed is not None:
        overrides["speed"] = args.speed
    if args.seed is not None:
        overrides["seed"] = args.seed
    return load_sim_settings(args.settings, args.vehicles, **overrides)


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    settings = load(args)
    scene = Scene.load(settings.scene)
    traffic = TrafficSim(scene, RoadNetwork(scene), settings.traffic, settings.seed, settings.tick_hz)
    dt_s = 1.0 / settings.tick_hz
    collision_every = max(1, round(settings.tick_hz / settings.collision_check_hz))
    with Node(conf, service="sim", instance=args.instance, scope=SCOPE, stop=shutdown.event) as node:
        gt_pub = node.publisher("ground_truth")
        clock_pub = node.publisher("sim_clock")
        calib_pubs = {agent: node.publisher("calibration", agent=agent) for agent in scene.agents}
        plans = (
            PlanClient(node, traffic, settings.plan_request_timeout_s)
            if settings.traffic.route_policy == "plan"
            else None
        )
        state = {"rtf": 0.0, "late_s": 0.0}

        def status() -> tuple[int, str]:
            level = DEGRADED if settings.speed > 0 and state["late_s"] > LATE_TOLERANCE_S else NOMINAL
            return level, (
                f"tick {traffic.tick}, sim {traffic.time_s:.1f} s, real-time factor {state['rtf']:.2f} "
                f"(target {settings.speed or 'max'}), {len(traffic.vehicles)} vehicles, "
                f"{sum(traffic.arrivals.values())} junction arrivals, {len(traffic.trips)} trips"
            )

        node.health.set_status(status)
        start_wall_ns = time.time_ns()
        start_mono = time.monotonic()
        rtf_mark = (start_mono, 0.0)
        next_clock = next_calib = 0.0
        last_log = start_mono
        log.info(
            "sim up: scene %s, %d vehicles, seed %d, %g Hz ticks, speed %s, route policy %s",
            scene.scene_id,
            len(traffic.vehicles),
            settings.seed,
            settings.tick_hz,
            settings.speed or "max",
            settings.traffic.route_policy,
        )
        while not shutdown.requested:
            if plans is not None:  # replies and pushes that arrived, then this tick's requests
                plans.tick(start_wall_ns + round(traffic.time_s * NS))
            t0 = time.time_ns()
            traffic.step()
            stamp_ns = start_wall_ns + round(traffic.time_s * NS)
            msg = ground_truth_message(traffic, scene, settings.seed, settings.tick_hz)
            stage = processing_stamp("sim/step", t0, time.time_ns())
            if settings.speed > 0:  # publish a tick at its stamp, not before (latencies stay >= 0)
                due = start_mono + traffic.time_s / settings.speed
                wait = due - time.monotonic()
                state["late_s"] = max(0.0, -wait)
                if wait > 0 and shutdown.wait(wait):
                    break
            header = gt_pub.next_header(stamp_ns=stamp_ns, tick=traffic.tick, frame_id="world")
            msg.header.CopyFrom(header)
            gt_pub.put(msg, header, stages=[stage])
            node.counters.inc("published/ground_truth")
            if traffic.tick % collision_every == 0:
                for pair in traffic.overlapping_pairs():
                    node.counters.inc("traffic/overlaps")
                    log.warning("vehicles overlap: %s", pair)
            now = time.monotonic()
            if traffic.time_s >= next_clock:
                next_clock += 1.0 / settings.clock_publish_hz
                if now - rtf_mark[0] >= RTF_WINDOW_S:
                    state["rtf"] = (traffic.time_s - rtf_mark[1]) / (now - rtf_mark[0])
                    rtf_mark = (now, traffic.time_s)
                clock = SimClock(
                    tick=traffic.tick, step_s=dt_s, real_time_factor=state["rtf"], lock_step=False
                )
                clock.sim_time.FromNanoseconds(stamp_ns)
                clock_pub.put(clock, stamp_ns=stamp_ns, tick=traffic.tick, frame_id="world")
            if traffic.time_s >= next_calib:
                next_calib += 1.0 / settings.calibration_publish_hz
                for agent, pub in calib_pubs.items():
                    pub.put(calibration_set(scene, agent), stamp_ns=stamp_ns, tick=traffic.tick)
            if now - last_log >= args.report_interval_s:
                log.info(
                    "sim %.1f s, real-time factor %.2f, %d junction arrivals, %d trips, %d detours%s",
                    traffic.time_s,
                    state["rtf"],
                    sum(traffic.arrivals.values()),
                    len(traffic.trips),
                    traffic.detours,
                    f"; plans {plans.summary()}" if plans is not None else "",
                )
                last_log = now
        if plans is not None:
            plans.close()
    return 0


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--settings", type=Path, default=DEFAULT_SIM_CONFIG, help="sim settings YAML")
    parser.add_argument("--speed", type=float, default=None, help="sim seconds per wall second (0 = max)")
    parser.add_argument("--seed", type=int, default=None, help="scenario seed")
    parser.add_argument("--vehicles", type=int, default=None, help="number of vehicles")
    parser.add_argument("--report-interval-s", type=float, default=10.0, help="log interval")


def cli(argv: list[str] | None = None) -> int:
    return run_service("sim", main, description=__doc__ or "", add_args=add_args, argv=argv)


if __name__ == "__main__":
    sys.exit(cli())

"""Vehicle client: one connected vehicle's plan client against a live system (`rmmdet vehicle`).

    python -m services.vehicle --instance v03 [--lane L --destination J] [--ros2 [--namespace /v03]]

The vehicle (its id is the instance) hears the plans the coordinator pushes to it and, given its lane
and destination, asks for one (again after 1, 2, 4, 8 s while unanswered). Each plan goes through the
checks every vehicle makes (shared/vehicle/plan_client.py: signed by a trusted coordinator key, id,
version, issued during this run, TTL); a refused one is counted and printed, never acknowledged. An
accepted one is printed (one line, or JSON with --json) and acknowledged with the vehicle's decision
(shared/vehicle/follower.py), and dropped at its TTL. With --ros2 the car decides: the plan goes to it
as a nav_msgs/Path on the key zenoh-bridge-ros2dds maps to its `/rmmdet/plan` topic, and its
rmmdet_msgs/PlanAck on `/rmmdet/plan_ack` becomes the RouteAck (shared/vehicle/ros2.py; the bridge's
configuration: deploy/ros2/). In the multi-site profile it runs as `vehicle-<id>` (its certificate):
it can ask for, hear and acknowledge its own plans only.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

import zenoh
from rmmdet.v1.common_pb2 import Header
from rmmdet.v1.planning_pb2 import RoutePlan, RouteRequest, RouteResponse

from services.vehicle.car import Report, Ros2Car, plan_fields
from shared.bus import names
from shared.bus.codec import MessageDecoder
from shared.bus.node import Node
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.config import load_settings
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.security.plan_signing import PlanVerifier
from shared.service import exit_process, run_service
from shared.shutdown import GracefulShutdown
from shared.traffic.plans import Ack
from shared.vehicle.config import VehicleSettings
from shared.vehicle.follower import PlanFollower
from shared.vehicle.plan_client import CheckedPushes, Outcome, PlanCheck, RequestRetry, VehicleLink

log = logging.getLogger("services.vehicle")

POLL_S = 0.05
OUTCOME_QUEUE = 16
PUSHED_QUEUE = 64


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    vehicle_id = args.instance
    settings = load_settings(VehicleSettings, None)
    settings.resolve_paths()
    network = RoadNetwork(Scene.load(settings.scene))
    if args.lane is not None and args.lane not in network.lanes:
        log.error("lane %r is not in the scene's road network", args.lane)
        return 2
    report = Report(sys.stdout, args.json)
    with Node(
        conf,
        service=names.VEHICLE,
        instance=vehicle_id,
        scope="vehicles",
        stop=shutdown.event,
        announce=False,
    ) as node:
        counters = node.counters
        verifier = PlanVerifier.watching(settings.plan_key_source())
        check = PlanCheck(verifier, settings.plan_max_ttl_s, counters, time.time_ns())
        outcomes = BoundedQueue[Outcome](
            OUTCOME_QUEUE, OverflowPolicy.DROP_OLDEST, counters, "dropped/outcomes"
        )
        pushed = CheckedPushes(vehicle_id, check, PUSHED_QUEUE, counters)
        decoder = MessageDecoder(RouteResponse, counters)
        link = VehicleLink(
            node, vehicle_id, settings.plan_request_timeout_s, check, decoder, outcomes, pushed
        )
        car = (
            Ros2Car(node.session, args.namespace or f"/{vehicle_id}", network, counters)
            if args.ros2
            else None
        )
        follower, retry = PlanFollower(network.lanes), RequestRetry()
        refused: dict[str, int] = {}
        handled = 0

        def ask() -> None:
            req = RouteRequest(
                current_lane_id=args.lane,
                destination_junction_id=args.destination or "",
                current_plan_version=follower.version,
            )
            link.request(req, time.time_ns())
            counters.inc("plans/requested")

        def offer(plan: RoutePlan, header: Header, how: str) -> None:
            nonlocal handled
            handled += 1
            if car is not None:
                try:
                    car.forward(plan, header)
                except ValueError as exc:  # a lane the car's road network lacks: it never becomes a Path
                    counters.inc("rejected/plan_unknown_lane")
                    acknowledge(plan, header, Ack.REJECTED_INVALID, str(exc), how)
                    return
                report(
                    "forwarded",
                    f"{how} plan {plan.plan_id} v{plan.version} to the car on {car.plan_key}",
                    **plan_fields(plan),
                )
                return
            decision = follower.consider(plan, time.time_ns())
            acknowledge(plan, header, decision.status, decision.reason, how)

        def acknowledge(plan: RoutePlan, header: Header, status: Ack, reason: str, how: str) -> None:
            link.acknowledge(plan.plan_id, plan.version, status, reason, header)
            counters.inc(f"acks/{status.name.lower()}")
            fields = plan_fields(plan)
            lanes, why = " ".join(fields["lanes"]), f" ({reason})" if reason else ""
            report(
                status.name.lower(),
                f"{how} plan {plan.plan_id} v{plan.version}: {status.name}{why}, "
                f"lanes {lanes}, valid {fields['valid_for_s']} s",
                how=how, reason=reason, **fields,
            )  # fmt: skip

        log.info(
            "vehicle %s up: %s", vehicle_id, f"ROS 2 car on {car.plan_key}" if car else "deciding itself"
        )
        if args.lane is not None:
            ask()
        deadline = time.monotonic() + args.duration_s if args.duration_s else None
        while not shutdown.requested:
            now_s = time.monotonic()
            for outcome in outcomes.drain():
                if outcome.plan is not None:
                    retry.answered(vehicle_id)
                    offer(outcome.plan, outcome.plan.header, "requested")
                else:
                    counters.inc(f"plans/{outcome.error}")
                    why = f" ({outcome.detail})" if outcome.detail else ""
                    report(
                        "no_plan",
                        f"request failed: {outcome.error}{why}",
                        error=outcome.error,
                        detail=outcome.detail,
                    )
                    if outcome.error == "no_reply" and not retry.unanswered(vehicle_id, now_s):
                        counters.inc("plans/given_up")
            if retry.due(now_s):
                ask()
            for received in pushed.drain():  # each checked on arrival (CheckedPushes)
                offer(received.message, received.header, "pushed")
            if car is not None:
                for plan, header, answer in car.answers():
                    follower.answered(plan, answer.status)
                    acknowledge(plan, header, answer.status, answer.reason, "car answered")
            if (ended := follower.expired(time.time_ns())) is not None:
                report("expired", f"plan {ended.plan_id} ran out: routing itself", plan_id=ended.plan_id)
            for name, count in counters.snapshot().items():
                if name.startswith("rejected/") and count > refused.get(name, 0):
                    report(
                        "refused",
                        f"{name.removeprefix('rejected/')} ({count} so far)",
                        reason=name,
                        count=count,
                    )
                    refused[name] = count
            if (args.plans and handled >= args.plans) or (deadline is not None and now_s >= deadline):
                break
            shutdown.wait(POLL_S)
        if car is not None:
            car.close()
        link.close()
    return 0


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--lane", help="the lane the vehicle is on: ask for a plan from it")
    parser.add_argument("--destination", help="junction to plan to (default: the coordinator's choice)")
    parser.add_argument("--ros2", action="store_true", help="forward plans to a ROS 2 car (deploy/ros2/)")
    parser.add_argument("--namespace", help="the car's bridge namespace (default: /<vehicle id>)")
    parser.add_argument("--json", action="store_true", help="one JSON object per line")
    parser.add_argument("--plans", type=int, default=0, help="exit after this many plans (0: run on)")
    parser.add_argument("--duration-s", type=float, default=0.0, help="exit after this long (0: run on)")


def cli(argv: list[str] | None = None) -> int:
    return run_service("vehicle", main, description=__doc__ or "", add_args=add_args, argv=argv)


if __name__ == "__main__":
    exit_process(cli())

"""The sim's fleet of connected vehicles on the bus (route_policy `plan`), each through the vehicle
library a real car runs (shared/vehicle/plan_client.py: its request, checks, retries, expiry, acks).

Each vehicle is a client of the coordinator: once per lane (`TrafficSim.needs_plan`) it sends a
RouteRequest on the route RPC key with a non-blocking query; the reply (or an error, or nothing by
`plan_request_timeout_s`) is queued by the Zenoh callback and applied on the next tick, so the 60 Hz
loop never waits for the network. A request that went unanswered (the router restarting) is asked again
after 1, 2, 4 and 8 s until one is answered (`RequestRetry`; `plans/retried`, `plans/given_up`). Plans
pushed on `rmmdet/v1/cloud/plans/<vehicle>` are applied the same way. A plan is considered only if the
coordinator's plan key signed it, its id is well formed, it was issued during this run (a plan's
version is its issue time: a replay from an earlier run is refused) and its TTL is within
`plan_max_ttl_s` (`plan_problem`); anything else is counted under `rejected/plan_<reason>` and not
acknowledged, and a reply that fails the checks does not stop the vehicle from taking a later, genuine
reply to the same request (a rogue second queryable cannot answer for the coordinator). Every plan
considered is answered with a RouteAck carrying the vehicle's decision (ACCEPTED, DUPLICATE,
REJECTED_STALE, REJECTED_INVALID), and the end of a followed plan too (COMPLETED once its last lane is
driven, REJECTED_INVALID when a detour leaves it: `TrafficSim.take_plan_ends`). Without a coordinator
vehicles keep driving: no plan means the shortest route, and a plan is followed only until its TTL
(`PlanExpiry`). When a coordinator's presence token appears (it started, or came back), every vehicle
asks at once.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Mapping
from pathlib import Path

import zenoh
from rmmdet.v1.common_pb2 import Header
from rmmdet.v1.planning_pb2 import RoutePlan, RouteRequest, RouteResponse

from shared.bus import names
from shared.bus.codec import MessageDecoder
from shared.bus.node import Node, Received
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.bus.streams import get_stream
from shared.security.identities import vehicle_identity
from shared.shutdown import GracefulShutdown
from shared.traffic.plans import Ack
from shared.vehicle.plan_client import JoinAsks, Outcome, PlanCheck, PlanExpiry, RequestRetry, VehicleLink
from sim.traffic import TrafficSim, Vehicle

log = logging.getLogger("services.sim.plans")

#: Outstanding replies held between ticks; more than one per vehicle only if ticks stall.
REPLY_QUEUE_PER_VEHICLE = 4
PUSHED_QUEUE = 1024  # pushed plans held between ticks


class PlanClient:
    def __init__(
        self,
        node: Node,
        traffic: TrafficSim,
        request_timeout_s: float,
        check: PlanCheck,
        vehicle_nodes: Mapping[str, Node] | None = None,
    ) -> None:
        """`vehicle_nodes`: each vehicle's own session (its identity, multi-site profile); without, every
        vehicle asks, acks and listens on the sim's `node` (one host)."""
        self.node = node
        self.traffic = traffic
        self.counters = node.counters
        self.check = check
        self.decoder = MessageDecoder(RouteResponse, node.counters)
        self.outcomes: BoundedQueue[Outcome] = BoundedQueue(
            REPLY_QUEUE_PER_VEHICLE * max(1, len(traffic.vehicles)),
            OverflowPolicy.DROP_OLDEST,
            node.counters,
            "dropped/plan_outcomes",
        )
        self.pushed: BoundedQueue[Received] = BoundedQueue(
            PUSHED_QUEUE, OverflowPolicy.DROP_OLDEST, node.counters, "dropped/pushed_plans"
        )
        if vehicle_nodes is None:  # one subscription hears every vehicle's pushes
            node.subscribe_stream("route_plan", queue=self.pushed)
        self.links = {
            v.id: VehicleLink(
                vehicle_nodes[v.id] if vehicle_nodes is not None else node,
                v.id,
                request_timeout_s,
                check,
                self.decoder,
                self.outcomes,
                self.pushed if vehicle_nodes is not None else None,  # each hears only its own
            )
            for v in traffic.vehicles
        }
        self.expiry = PlanExpiry()
        # A coordinator that (re)appears serves every vehicle at once, from the vehicles' own state
        # (current lane, destination, followed version): nobody waits for its next lane to be re-planned.
        # Leaves are not held: the rejoin after a router restart re-serves what failed meanwhile.
        self.coordinators = node.presence(
            get_stream("alive").pattern(scope="cloud", service=names.COORDINATOR), hold_leaves=False
        )
        self.retry = RequestRetry()
        self.join_asks = JoinAsks()
        self._by_id = {v.id: v for v in traffic.vehicles}
        # Each vehicle's last plan end (plan id, status), repeated in its requests (`ended_plan_id`).
        self._ended: dict[str, tuple[str, Ack]] = {}

    def close(self) -> None:
        for link in self.links.values():
            link.close()

    def summary(self) -> dict[str, int]:
        """Request and acknowledgement counters, for the periodic log."""
        return {k: v for k, v in self.counters.snapshot().items() if k.startswith(("plans/", "acks/"))}

    # --- per tick --------------------------------------------------------------------------------

    def tick(self, stamp_ns: int) -> None:
        """Apply what arrived since the last tick, then send this tick's requests."""
        now_s = time.monotonic()
        for outcome in self.outcomes.drain():
            if outcome.plan is None:
                self.counters.inc(f"plans/{outcome.error}")
                if outcome.error == "no_reply" and not self.retry.unanswered(outcome.vehicle_id, now_s):
                    self.counters.inc("plans/given_up")
            else:
                self.counters.inc("plans/replied")
                self.retry.answered(outcome.vehicle_id)
                self.apply(outcome.plan)
        for vehicle_id in self.retry.due(now_s):
            self.counters.inc("plans/retried")
            self._by_id[vehicle_id].ask_now = True
        for received in self.pushed.drain():
            self.counters.inc("plans/pushed_received")
            self.apply_pushed(received)
        for vehicle_id in self.expiry.expired(time.time_ns()):
            self.counters.inc("plans/expired")
            self.traffic.drop_plan(vehicle_id)
        for end in self.traffic.take_plan_ends():  # completed or left by a detour: the coordinator is told
            self.acknowledge(end.vehicle_id, end.plan_id, end.version, end.status, end.reason, stamp_ns)
            self._ended[end.vehicle_id] = (end.plan_id, end.status)
        # The coordinator declares its token once its route RPC answers (services/coordinator/main.py).
        if any(alive for _, alive in self.coordinators.changes()):
            self.counters.inc("plans/coordinator_joined")
            self.join_asks.joined()
        if self.join_asks.due(now_s):
            for v in self.traffic.vehicles:
                v.ask_now = True
        for v in self.traffic.vehicles:
            if self.traffic.needs_plan(v):
                v.planned_lane = v.lane_id  # one request per lane, answered or not
                v.ask_now = False
                self.request(v, stamp_ns)

    def request(self, v: Vehicle, stamp_ns: int) -> None:
        lane, progress_m = self.traffic.plan_origin(v)
        req = RouteRequest(
            current_lane_id=lane,
            lane_progress_m=progress_m,
            destination_junction_id=self.traffic.routing_destination(v),
            current_plan_version=v.plan_version,
        )
        if v.id in self._ended:  # said again here: this request may overtake that ack
            req.ended_plan_id, status = self._ended[v.id]
            req.ended_status = status.value  # type: ignore[assignment]
        req.position_m.x_m, req.position_m.y_m = v.x, v.y
        self.links[v.id].request(req, stamp_ns)
        self.counters.inc("plans/requested")

    def apply_pushed(self, received: Received) -> None:
        plan: RoutePlan = received.message
        if (get_stream("route_plan").ids(received.key) or {}).get("vehicle") != plan.vehicle_id:
            self.counters.inc("rejected/plan_key_mismatch")
            return
        if self.check.accept(plan, pushed=True):
            self.apply(plan)

    def apply(self, plan: RoutePlan) -> None:
        """Hand the plan to its vehicle and acknowledge with the vehicle's decision."""
        if plan.vehicle_id not in self.links:
            self.counters.inc("rejected/plan_unknown_vehicle")
            return
        reason = ""
        if plan.HasField("valid_until") and plan.valid_until.ToNanoseconds() < time.time_ns():
            status, reason = Ack.REJECTED_STALE, "expired"
        else:
            lanes = list(plan.lane_ids)
            status = self.traffic.set_plan(plan.vehicle_id, lanes, int(plan.version), plan.plan_id)
            if status is Ack.ACCEPTED:
                self.expiry.followed(plan.vehicle_id, plan.valid_until.ToNanoseconds())
            if status is Ack.REJECTED_INVALID:
                reason = "route does not continue from the vehicle's lane"
        self.acknowledge(plan.vehicle_id, plan.plan_id, plan.version, status, reason, plan.header)

    def acknowledge(
        self, vehicle_id: str, plan_id: str, version: int, status: Ack, reason: str, stamp: Header | int
    ) -> None:
        """Publish the vehicle's RouteAck (`VehicleLink.acknowledge`), counted by status."""
        self.counters.inc(f"acks/{status.name.lower()}")
        self.links[vehicle_id].acknowledge(plan_id, version, status, reason, stamp)


def missing_vehicle_configs(configs: Path, traffic: TrafficSim) -> list[str]:
    """The vehicles of `traffic` without an identity config (`<configs>/vehicle-<id>.json`)."""
    return [v.id for v in traffic.vehicles if not (configs / f"{vehicle_identity(v.id)}.json").is_file()]


def open_vehicle_nodes(
    configs: Path, traffic: TrafficSim, node: Node, shutdown: GracefulShutdown, stack: contextlib.ExitStack
) -> dict[str, Node]:
    """Each vehicle's own session, from `<configs>/vehicle-<id>.json` (its identity's Zenoh config):
    the vehicle asks for, hears and acknowledges its plans as itself, as a car would; the sim's own
    identity holds no vehicle's rights. Counted into the sim's counters; no presence of their own."""
    nodes = {}
    for v in traffic.vehicles:
        vehicle_node = Node(
            zenoh.Config.from_file(str(configs / f"{vehicle_identity(v.id)}.json")),
            service=names.VEHICLE,
            instance=v.id,
            scope="vehicles",
            stop=shutdown.event,
            announce=False,
            counters=node.counters,
        )
        nodes[v.id] = stack.enter_context(vehicle_node)
    log.info("%d vehicles on their own identities (%s)", len(nodes), configs)
    return nodes

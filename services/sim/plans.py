"""The connected vehicles' side of route planning on the bus (route_policy `plan`).

Each vehicle is a client of the coordinator: once per lane (`TrafficSim.needs_plan`) it sends a
RouteRequest on the route RPC key with a non-blocking query; the reply (or an error, or nothing by
`plan_request_timeout_s`) is queued by the Zenoh callback and applied on the next tick, so the 60 Hz
loop never waits for the network. A request that went unanswered (the router restarting) is asked again
after 1, 2, 4 and 8 s until one is answered (`RequestRetry`; `plans/retried`, `plans/given_up`). Plans
pushed on `rmmdet/@v1/cloud/plans/<vehicle>` are applied the same way. A plan is considered only if the
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

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import cast

import zenoh
from google.protobuf.message import DecodeError
from rmmdet.v1.common_pb2 import ErrorCode, ErrorResponse, Header
from rmmdet.v1.planning_pb2 import RouteAck, RoutePlan, RouteRequest, RouteResponse

from shared.bus.codec import Counters, MessageDecoder, encode
from shared.bus.node import Node, Publisher, Received
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.bus.streams import get_stream
from shared.security.plan_signing import PlanVerifier
from shared.traffic.plans import Ack, plan_problem
from sim.traffic import TrafficSim, Vehicle

log = logging.getLogger("services.sim.plans")

#: Outstanding replies held between ticks; more than one per vehicle only if ticks stall.
REPLY_QUEUE_PER_VEHICLE = 4
PUSHED_QUEUE = 1024  # pushed plans held between ticks
#: After a coordinator's presence token appears, every vehicle asks for a plan this much later, wall s:
#: the token comes with its session, the route queryable a moment after.
REASK_AFTER_JOIN_S = 0.3
ERROR_NAMES = {v: ErrorCode.Name(v).removeprefix("ERROR_CODE_").lower() for v in ErrorCode.values()}


@dataclass(frozen=True)
class Outcome:
    """A finished request: the plan, or why there is none (`error` names the counter)."""

    vehicle_id: str
    plan: RoutePlan | None
    error: str = ""


class PlanCheck:
    """`plan_problem` with the vehicles' trusted keys and TTL bound; counts what it refuses. Called on
    Zenoh threads (replies) and the main loop (pushes): stateless but for the thread-safe counters."""

    def __init__(
        self, verifier: PlanVerifier, max_ttl_s: float, counters: Counters, run_start_ns: int = 0
    ) -> None:
        self.verifier = verifier
        self.max_ttl_s = max_ttl_s
        self.counters = counters
        self.run_start_ns = run_start_ns  # plans issued before this run are replays (plan_before_run)

    def accept(self, plan: RoutePlan) -> bool:
        problem = plan_problem(plan, self.verifier, time.time_ns(), self.max_ttl_s, self.run_start_ns)
        if problem is not None:
            self.counters.inc(f"rejected/{problem}")
        return problem is None


class PlanExpiry:
    """When each vehicle's followed plan runs out (`valid_until`, wall ns): the plan is dropped then and
    the vehicle routes itself by the shortest route, as with no coordinator, until a new plan comes (it
    asks at its next lane as always). A coordinator that is gone therefore steers nobody for longer than
    its plans' TTL (`plan_ttl_s`, 120 s)."""

    def __init__(self) -> None:
        self._until_ns: dict[str, int] = {}

    def followed(self, vehicle_id: str, valid_until_ns: int) -> None:
        self._until_ns[vehicle_id] = valid_until_ns

    def expired(self, now_ns: int) -> list[str]:
        """Vehicles whose plan ran out by `now_ns` (each reported once)."""
        out = [v for v, until in self._until_ns.items() if until <= now_ns]
        for v in out:
            del self._until_ns[v]
        return out


class RequestRetry:
    """When a vehicle asks again after a request went unanswered (`no_reply`: the router restarting, the
    coordinator not reachable for a moment): after `first_s`, doubling, at most `attempts` times in a
    row; an answer clears it. Monotonic seconds."""

    def __init__(self, first_s: float = 1.0, attempts: int = 4) -> None:
        self.first_s, self.attempts = first_s, attempts
        self._tries: dict[str, int] = {}
        self._due_s: dict[str, float] = {}

    def unanswered(self, vehicle_id: str, now_s: float) -> bool:
        """A request of `vehicle_id` went unanswered: True if another is scheduled, False if it gives up."""
        tries = self._tries.get(vehicle_id, 0)
        if tries >= self.attempts:
            self.answered(vehicle_id)
            return False
        self._tries[vehicle_id] = tries + 1
        self._due_s[vehicle_id] = now_s + self.first_s * 2**tries
        return True

    def answered(self, vehicle_id: str) -> None:
        self._tries.pop(vehicle_id, None)
        self._due_s.pop(vehicle_id, None)

    def due(self, now_s: float) -> list[str]:
        """Vehicles to ask again now (each once per scheduled retry)."""
        out = [v for v, t in self._due_s.items() if t <= now_s]
        for v in out:
            del self._due_s[v]
        return out


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
        rpc = get_stream("route_rpc")

        # One querier per vehicle, on its own key, declared for the whole run (declaring per request
        # would churn declarations). Every queryable on the key is asked (target ALL: Zenoh's default
        # asks only a "complete" one when there is one, which any client may declare) and every reply
        # is delivered as it comes (no consolidation: by default replies on one key are held and only
        # the newest is delivered, so a rogue replying last would hide the coordinator's): the first
        # valid reply is taken.
        def node_of(vehicle_id: str) -> Node:
            return vehicle_nodes[vehicle_id] if vehicle_nodes is not None else node

        self.queriers = {
            v.id: node_of(v.id).session.declare_querier(
                rpc.key(vehicle=v.id),
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=request_timeout_s,
                **rpc.qos.publisher_kwargs(),
            )
            for v in traffic.vehicles
        }
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
        if vehicle_nodes is None:
            node.subscribe_stream("route_plan", queue=self.pushed)
        else:  # each vehicle hears only its own plans
            for v in traffic.vehicles:
                vehicle_nodes[v.id].subscribe_stream("route_plan", queue=self.pushed, vehicle=v.id)
        self.ack_pubs: dict[str, Publisher] = {
            v.id: node_of(v.id).publisher("route_ack", vehicle=v.id, source_id=f"vehicles/{v.id}")
            for v in traffic.vehicles
        }
        self._request_seq: dict[str, int] = dict.fromkeys(self.ack_pubs, 0)
        self.expiry = PlanExpiry()
        # A coordinator that (re)appears serves every vehicle at once, from the vehicles' own state
        # (current lane, destination, followed version): nobody waits for its next lane to be re-planned.
        # Leaves are not held: the rejoin after a router restart re-serves what failed meanwhile.
        self.coordinators = node.presence(
            get_stream("alive").pattern(scope="cloud", service="coordinator"), hold_leaves=False
        )
        self._ask_all_at: float | None = None
        self.retry = RequestRetry()
        self._by_id = {v.id: v for v in traffic.vehicles}

    def close(self) -> None:
        for querier in self.queriers.values():
            querier.undeclare()

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
        if any(alive for _, alive in self.coordinators.changes()):
            self.counters.inc("plans/coordinator_joined")
            self._ask_all_at = time.monotonic() + REASK_AFTER_JOIN_S
        if self._ask_all_at is not None and time.monotonic() >= self._ask_all_at:
            self._ask_all_at = None
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
            vehicle_id=v.id,
            current_lane_id=lane,
            lane_progress_m=progress_m,
            destination_junction_id=self.traffic.routing_destination(v),
            current_plan_version=v.plan_version,
        )
        req.position_m.x_m, req.position_m.y_m = v.x, v.y
        self._request_seq[v.id] += 1
        req.header.source_id = f"vehicles/{v.id}"
        req.header.seq = self._request_seq[v.id]
        req.header.stamp.FromNanoseconds(stamp_ns)
        req.header.frame_id = "world"
        encoded = encode(req)
        handler = _ReplyHandler(v.id, self.decoder, self.outcomes, self.check)
        self.queriers[v.id].get(
            zenoh.handlers.Callback(handler.on_reply, handler.on_done),
            payload=encoded.payload,
            encoding=encoded.encoding,
        )
        self.counters.inc("plans/requested")

    def apply_pushed(self, received: Received) -> None:
        plan: RoutePlan = received.message
        if (get_stream("route_plan").ids(received.key) or {}).get("vehicle") != plan.vehicle_id:
            self.counters.inc("rejected/plan_key_mismatch")
            return
        if self.check.accept(plan):
            self.apply(plan)

    def apply(self, plan: RoutePlan) -> None:
        """Hand the plan to its vehicle and acknowledge with the vehicle's decision."""
        if plan.vehicle_id not in self.ack_pubs:
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
        """Publish the vehicle's RouteAck; `stamp`: the plan's header (the ack keeps its data stamp) or,
        for a plan's end, the tick's stamp in ns."""
        self.counters.inc(f"acks/{status.name.lower()}")
        ack = RouteAck(
            vehicle_id=vehicle_id,
            plan_id=plan_id,
            version=version,
            status=status.value,  # Ack mirrors AckStatus
            reason=reason,
        )
        if isinstance(stamp, Header):
            self.ack_pubs[vehicle_id].put(ack, derived_from=stamp)
        else:
            self.ack_pubs[vehicle_id].put(ack, stamp_ns=stamp)


class _ReplyHandler:
    """Callbacks of one request. They run on Zenoh threads: decode and enqueue only."""

    def __init__(
        self, vehicle_id: str, decoder: MessageDecoder, outcomes: BoundedQueue[Outcome], check: PlanCheck
    ) -> None:
        self.vehicle_id = vehicle_id
        self.decoder = decoder
        self.outcomes = outcomes
        self.check = check
        self.answered = False
        self.failed = False  # an error or bad reply was reported: no `no_reply` on top of it

    def on_reply(self, reply: zenoh.Reply) -> None:
        """The first valid reply is the answer. Every reply is checked, also after the answer: a rogue
        queryable's forged plans are refused and counted whether they come before the coordinator's
        reply or after it; a valid extra reply is counted (`plans/extra_replies`) and not applied."""
        try:
            if reply.ok is not None:
                sample = reply.ok
                attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
                decoded = self.decoder.decode(sample.payload.to_bytes(), str(sample.encoding), attachment)
                if decoded is None:  # counted by the decoder as rejected/<reason>
                    self._fail("bad_reply")
                    return
                response = cast(RouteResponse, decoded.message)
                if response.plan.vehicle_id != self.vehicle_id:
                    self.check.counters.inc("rejected/plan_wrong_vehicle")
                elif self.check.accept(response.plan):  # else counted; a genuine reply may follow
                    if self.answered:
                        self.check.counters.inc("plans/extra_replies")
                    else:
                        self.answered = True
                        self.outcomes.put(Outcome(self.vehicle_id, response.plan))
                return
            error = ErrorResponse()
            try:
                error.ParseFromString(reply.err.payload.to_bytes() if reply.err is not None else b"")
            except DecodeError:
                error.code = ErrorCode.ERROR_CODE_UNSPECIFIED
            self._fail(f"error_{ERROR_NAMES.get(error.code, 'other')}")
        except Exception:  # never raise into Zenoh's thread
            log.exception("route reply for %s failed", self.vehicle_id)
            self._fail("bad_reply")

    def _fail(self, error: str) -> None:
        """Report the first failure only, and none after the answer (a valid reply may still come and is
        taken then)."""
        if not self.failed and not self.answered:
            self.failed = True
            self.outcomes.put(Outcome(self.vehicle_id, None, error))

    def on_done(self) -> None:
        if not self.answered and not self.failed:
            self.outcomes.put(Outcome(self.vehicle_id, None, "no_reply"))

"""A connected vehicle's side of route planning on the bus: the library the sim's vehicles use and a
real car runs (`rmmdet vehicle`).

`VehicleLink` is one vehicle's plumbing on a Node (its own session, or a shared one in the sim): a
non-blocking route request on the RPC key (target ALL, no consolidation: every reply is checked and
the first valid one is the answer, so a rogue queryable can neither answer for the coordinator nor
hide its reply), its pushed plans (`rmmdet/v1/cloud/plans/<vehicle>`), and its RouteAck publisher.
Replies and pushes are queued by Zenoh's threads and taken by the caller's loop. What a vehicle
trusts is decided here too: `PlanCheck` (signature by a trusted coordinator key, plan id, version
range, issued during this run, TTL within bound; shared/traffic/plans.py `plan_problem`), `PlanExpiry`
(a followed plan is dropped at its TTL: a gone coordinator steers nobody for longer) and `RequestRetry`
(a request unanswered across a router restart is asked again after 1, 2, 4, 8 s).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import cast

import zenoh
from google.protobuf.message import DecodeError
from rmmdet.v1.common_pb2 import ErrorCode, ErrorResponse, Header
from rmmdet.v1.planning_pb2 import RouteAck, RoutePlan, RouteRequest, RouteResponse

from shared.bus.codec import Counters, MessageDecoder, encode
from shared.bus.node import Node, Received
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.bus.streams import get_stream
from shared.security.plan_signing import PlanVerifier
from shared.traffic.plans import Ack, plan_problem

log = logging.getLogger(__name__)

MAX_DETAIL_CHARS = 200  # of an error reply's message, kept for the vehicle's report
ERROR_NAMES = {v: ErrorCode.Name(v).removeprefix("ERROR_CODE_").lower() for v in ErrorCode.values()}


@dataclass(frozen=True)
class Outcome:
    """A finished request: the plan, or why there is none (`error` names the counter)."""

    vehicle_id: str
    plan: RoutePlan | None
    error: str = ""
    detail: str = ""  # the coordinator's words, for an error reply (bounded by the codec's string limit)


class PlanCheck:
    """`plan_problem` with the vehicles' trusted keys and TTL bound; counts what it refuses. Called on
    Zenoh threads (replies) and the main loop (pushes).

    A pushed plan is taken only from the signer (`PlanVerifier.signer`) of the last plan that answered
    the vehicle's own request: the coordinator, or the shard that holds the vehicle (the owner of the
    lane it asked from). Any shard's key is trusted, so without this rule one shard's host could steer a
    vehicle another shard holds; one it never answered takes no pushes (`push_not_holder`)."""

    def __init__(
        self, verifier: PlanVerifier, max_ttl_s: float, counters: Counters, run_start_ns: int = 0
    ) -> None:
        self.verifier = verifier
        self.max_ttl_s = max_ttl_s
        self.counters = counters
        self.run_start_ns = run_start_ns  # plans issued before this run are replays (plan_before_run)
        self._holder: dict[str, str | None] = {}  # vehicle -> signer of its last answer (its own ids)

    def accept(self, plan: RoutePlan, pushed: bool = False) -> bool:
        """Whether to take `plan`, a reply to the vehicle's request or (`pushed`) a push."""
        problem = plan_problem(plan, self.verifier, time.time_ns(), self.max_ttl_s, self.run_start_ns)
        if problem is None and pushed and self._holder.get(plan.vehicle_id, "") != self.verifier.signer(plan):
            problem = "push_not_holder"
        if problem is not None:
            self.counters.inc(f"rejected/{problem}")
        return problem is None

    def answered(self, plan: RoutePlan) -> None:
        """`plan` (accepted) is the answer to its vehicle's request: its signer holds the vehicle now."""
        self._holder[plan.vehicle_id] = self.verifier.signer(plan)


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


class JoinAsks:
    """When every vehicle asks again because a coordinator's presence token appeared: at once for a join
    after a quiet `min_interval_s`, else once that interval after the last ask-all. A token that flaps (a
    forger declaring and dropping one, a link bouncing) then costs one round of requests per interval,
    not one per sim tick. Monotonic seconds."""

    def __init__(self, min_interval_s: float = 1.0) -> None:
        self.min_interval_s = min_interval_s
        self._last_s: float | None = None
        self._pending = False

    def joined(self) -> None:
        self._pending = True

    def due(self, now_s: float) -> bool:
        """True when every vehicle should ask now (then not again before `min_interval_s`)."""
        if not self._pending or (self._last_s is not None and now_s - self._last_s < self.min_interval_s):
            return False
        self._pending, self._last_s = False, now_s
        return True


class CheckedPushes(BoundedQueue[Received]):
    """A vehicle's pushed plans, each checked (`PlanCheck.accept`: signature, key, TTL, version, run)
    on arrival, before it takes a place: refused ones are counted and never queued, so a flood of
    forged pushes cannot evict a genuine one from the bounded queue (it did: checked only when taken)."""

    def __init__(self, vehicle_id: str, check: PlanCheck, maxsize: int, counters: Counters) -> None:
        super().__init__(maxsize, OverflowPolicy.DROP_OLDEST, counters, "dropped/pushed")
        self.vehicle_id, self.check, self._counters_in = vehicle_id, check, counters

    def put(self, item: Received) -> bool:
        plan = item.message
        if plan.vehicle_id != self.vehicle_id:
            self._counters_in.inc("rejected/plan_key_mismatch")
            return False
        if not self.check.accept(plan, pushed=True):  # counted by the check
            return False
        return super().put(item)


class VehicleLink:
    """One vehicle's route RPC querier, pushed-plan subscription and ack publisher on `node`. Replies
    (`Outcome`s, checked by `check`) go to `outcomes`; pushed plans to `pushed` (a `CheckedPushes`
    checks them on arrival). `subscribe_pushed=False`: the caller hears every vehicle's pushes at once."""

    def __init__(
        self,
        node: Node,
        vehicle_id: str,
        request_timeout_s: float,
        check: PlanCheck,
        decoder: MessageDecoder,
        outcomes: BoundedQueue[Outcome],
        pushed: BoundedQueue[Received] | None = None,
    ) -> None:
        self.vehicle_id = vehicle_id
        self.check, self.decoder, self.outcomes = check, decoder, outcomes
        rpc = get_stream("route_rpc")
        # Declared once for the run (declaring per request would churn declarations).
        self.querier = node.session.declare_querier(
            rpc.key(vehicle=vehicle_id),
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=request_timeout_s,
            **rpc.qos.publisher_kwargs(),
        )
        if pushed is not None:
            node.subscribe_stream("route_plan", queue=pushed, vehicle=vehicle_id)
        self.ack_pub = node.publisher("route_ack", vehicle=vehicle_id, source_id=f"vehicles/{vehicle_id}")
        self.seq = 0

    def close(self) -> None:
        self.querier.undeclare()

    def request(self, req: RouteRequest, stamp_ns: int) -> None:
        """Ask for a plan (non-blocking): the answer, an error or `no_reply` arrives in `outcomes`."""
        self.seq += 1
        req.vehicle_id = self.vehicle_id
        req.header.source_id = f"vehicles/{self.vehicle_id}"
        req.header.seq = self.seq
        req.header.stamp.FromNanoseconds(stamp_ns)
        req.header.frame_id = "world"
        encoded = encode(req)
        handler = ReplyHandler(self.vehicle_id, self.decoder, self.outcomes, self.check)
        self.querier.get(
            zenoh.handlers.Callback(handler.on_reply, handler.on_done),
            payload=encoded.payload,
            encoding=encoded.encoding,
        )

    def acknowledge(self, plan_id: str, version: int, status: Ack, reason: str, stamp: Header | int) -> None:
        """Publish the vehicle's RouteAck; `stamp`: the plan's header (the ack keeps its data stamp) or a
        stamp in ns (a plan's end)."""
        ack = RouteAck(
            vehicle_id=self.vehicle_id,
            plan_id=plan_id,
            version=version,
            status=status.value,  # Ack mirrors AckStatus
            reason=reason,
        )
        if isinstance(stamp, Header):
            self.ack_pub.put(ack, derived_from=stamp)
        else:
            self.ack_pub.put(ack, stamp_ns=stamp)


class ReplyHandler:
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
                        self.check.answered(response.plan)
                        self.outcomes.put(Outcome(self.vehicle_id, response.plan))
                return
            error = ErrorResponse()
            try:
                error.ParseFromString(reply.err.payload.to_bytes() if reply.err is not None else b"")
            except DecodeError:
                # Not the coordinator's answer: Zenoh's own error reply (b"Timeout" when the query got
                # no reply in time, e.g. across a router restart). No answer, then: `on_done` reports
                # no_reply and the vehicle asks again (it was reported as error_unspecified, not retried).
                self.check.counters.inc("plans/transport_errors")
                return
            self._fail(f"error_{ERROR_NAMES.get(error.code, 'other')}", error.message[:MAX_DETAIL_CHARS])
        except Exception:  # never raise into Zenoh's thread
            log.exception("route reply for %s failed", self.vehicle_id)
            self._fail("bad_reply")

    def _fail(self, error: str, detail: str = "") -> None:
        """Report the first failure only, and none after the answer (a valid reply may still come and is
        taken then)."""
        if not self.failed and not self.answered:
            self.failed = True
            self.outcomes.put(Outcome(self.vehicle_id, None, error, detail))

    def on_done(self) -> None:
        if not self.answered and not self.failed:
            self.outcomes.put(Outcome(self.vehicle_id, None, "no_reply"))

"""The coordinator's bus side: object lists, presence and acks into `CoordinatorCore`, maps and pushed
plans out, the route RPC's handler, the main loop (services/coordinator/main.py starts it)."""

from __future__ import annotations

import logging
import time

from rmmdet.v1.planning_pb2 import RoutePlan, RouteRequest, RouteResponse

from services.coordinator.newcomers import admit_newcomer, newcomer_admission
from services.coordinator.shard import ShardLink
from shared.bus import names
from shared.bus.health import worst
from shared.bus.liveliness import agent_of_mec_token
from shared.bus.node import Node, Received, processing_stamp
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.bus.rpc import RpcRejected
from shared.bus.streams import get_stream, limits
from shared.bus.uplink import REJOIN_GRACE_S
from shared.logging_setup import ReportTimer
from shared.security.plan_signing import PlanSigner
from shared.shutdown import GracefulShutdown
from shared.timebase import SimTime
from shared.traffic.config import CoordinatorSettings
from shared.traffic.core import CoordinatorCore, RequestRejected

log = logging.getLogger("services.coordinator")

STAGE = "coordinator"
#: Longest idle wait of the main loop: presence changes are picked up at least this often.
POLL_S = 0.05
OBJECTS, ACKS = get_stream("objects"), get_stream("route_ack")
#: Bytes an object may take in an object list's payload: a tracked object with every field set (three
#: class hypotheses, both covariances) serialises to 325 B. A list over `max_objects_per_list` of these
#: is refused unparsed (`rejected/oversize`): parsing and range-checking a forged list of 100k objects
#: (7.5 MB) held the subscriber thread ~0.6 s, so the agent's genuine lists came late (STALE), and grew
#: the process by ~20 MB.
MAX_OBJECT_BYTES = 1024
SERVED_COPIES_QUEUE = 256  # plans served between two rounds of the loop, to copy for viewers


class CoordinatorService:
    """The main loop: ingest objects, presence and acks; rebuild and publish maps; push plans."""

    def __init__(
        self,
        node: Node,
        core: CoordinatorCore,
        settings: CoordinatorSettings,
        clock: SimTime,
        signer: PlanSigner,
        shard: ShardLink | None = None,
    ) -> None:
        self.node, self.core, self.settings, self.clock = node, core, settings, clock
        self.signer = signer
        self.shard = shard
        self.newcomers = shard.newcomers if shard is not None else newcomer_admission(settings)
        self.counters = node.counters
        # Object lists older than the stale threshold on arrival would not make their agent LIVE; lists
        # too large to hold `limits.max_objects_per_list` objects are refused before they are parsed.
        bus_limits = limits()
        objects: BoundedQueue[Received] = BoundedQueue(
            settings.service.objects_queue_per_agent * max(1, len(core.agents)),
            OverflowPolicy.DROP_OLDEST,
            node.counters,
        )
        # Unsharded every agent's key; a shard its own agents' only.
        for key in [OBJECTS.pattern()] if shard is None else [OBJECTS.key(agent=a) for a in core.agents]:
            node.subscribe(
                key,
                OBJECTS.message_type,
                queue=objects,
                max_age_s=settings.coverage.stale_after_s,
                max_payload_bytes=bus_limits.max_objects_per_list * MAX_OBJECT_BYTES,
                clock_s=clock.now_s,
                max_future_s=bus_limits.max_clock_skew_s,
            )
        self.objects = objects
        # Acks carry their plan's stamp (or a plan end's tick): the coordinator's clock of record.
        self.acks = node.subscribe_stream(
            "route_ack", clock_s=clock.now_s, max_future_s=bus_limits.max_clock_skew_s
        )
        # Plans served over the RPC, copied for viewers by the main loop (the handler runs on a Zenoh
        # thread, where declaring and putting can stall the session).
        self.served: BoundedQueue[tuple[RoutePlan, int]] = BoundedQueue(
            SERVED_COPIES_QUEUE, OverflowPolicy.DROP_OLDEST, node.counters, "dropped/plan_copies"
        )
        self.presence = node.presence(get_stream("alive").pattern(service=names.MEC))
        # The vehicles' process (the sim): when it leaves, their plans end (CoordinatorCore.vehicles_left).
        self.vehicles_presence = node.presence(get_stream("alive").pattern(scope="sim", service=names.SIM))
        # Object lists and the sim clock come tens of times a second: all of them silent at once is a
        # frozen link (docs/reliability.md R2), held like a cut one.
        node.uplink.expect_traffic(settings.coverage.bus_silent_after_s, settings.coverage.bus_silence_max_s)
        self.map_pub = (
            node.publisher("traffic_map")
            if shard is None
            else node.publisher("region_map", region=str(shard.region))
        )
        node.health.set_status(self.health)  # Zenoh thread: cached values only

    def health(self) -> tuple[int, str]:
        """The core's health, or the shard's when it is worse (cached values only: a Zenoh thread)."""
        level, message = self.core.health()
        other = self.shard.health() if self.shard is not None else None
        if other is None:
            return level, message
        return worst(level, other[0]), f"{message}; {other[1]}"

    def plan(self, request: RouteRequest, start_ns: int) -> tuple[RouteResponse, int]:
        """The route RPC's handler (Zenoh thread; the core's lock guards its state)."""
        if self.shard is not None:
            self.shard.gate(request)  # another region's lane: declined; a vehicle not held: deferred
        elif not self.core.owns_vehicle(request.vehicle_id):
            admit_newcomer(self.newcomers, request.vehicle_id)
        self.record_objects()  # a plan includes every list that reached the process before the request
        ended = self.core.ended_by_request
        try:
            plan, stamp_ns = self.core.serve(request, self.clock.now_s(), start_ns)
        except RequestRejected as err:
            raise RpcRejected(err.reason, err.code, err.message) from None
        finally:
            if self.core.ended_by_request > ended:  # the request overtook its vehicle's plan-end ack
                self.counters.inc("plans/ended_by_request")
        signed = self.signer.sign(plan)
        copy = RoutePlan()
        copy.CopyFrom(signed)  # published later, with its own header: not the core's plan
        self.served.put((copy, stamp_ns))
        return RouteResponse(plan=signed), stamp_ns

    def copy_for_viewers(self) -> None:
        """Viewers see the plans vehicles asked for too (pushed ones they see on route_plan): a copy
        on route_plan_served while something subscribes there. Never at the vehicle's expense: a
        failure here is counted."""
        for plan, stamp_ns in self.served.drain():
            try:
                pub = self.node.publisher("route_plan_served", vehicle=plan.vehicle_id)
                if pub.has_subscribers():
                    pub.put(plan, stamp_ns=stamp_ns or time.time_ns(), frame_id="world")
                    self.counters.inc("plans/copied")
            except Exception as err:  # a viewer's copy must never fail the coordinator
                self.counters.inc("plans/copy_failed")
                log.warning("copy of %s's plan for viewers failed: %s", plan.vehicle_id, err)

    def run(self, shutdown: GracefulShutdown) -> None:
        report = ReportTimer(self.settings.report_interval_s, self.clock.now_s)
        silent = False
        while not shutdown.requested:
            self.node.health.beat()
            self.ingest(min(POLL_S, self.core.next_map_s - self.clock.now_s()))
            now = self.clock.now_s()
            # Cut off from the bus (a router restart or freeze) or only just back: the agents are not to
            # blame.
            if self.node.uplink.silent() != silent:
                silent = not silent
                if silent:
                    log.warning("nothing heard from the bus: link suspected (frozen router?), coverage held")
            self.core.hold_coverage(self.node.uplink.recovering(REJOIN_GRACE_S), now)
            tick = self.core.tick(now, time.time_ns())
            if tick.coverage is not None:
                log.warning("coverage: %s", ", ".join(f"{a} {s.value}" for a, s in tick.coverage.items()))
            if self.shard is not None:
                self.shard.poll(now)
            if tick.publish_map:
                self.publish_map(now)
                if self.shard is not None:
                    self.shard.publish_clique(now)
            if tick.replanned:
                log.info("replan: %d plans to push", tick.replanned)
            self.push(now)
            self.copy_for_viewers()
            if report.due():
                log.info(
                    "%s, %d vehicles evicted; counters %s",
                    self.core.health()[1],
                    self.core.vehicles_evicted,
                    self.counters.snapshot(),
                )

    def ingest(self, wait_s: float) -> None:
        """Wait up to `wait_s` for object lists, then take everything queued: lists, presence, acks."""
        first = self.objects.get(timeout=max(0.0, wait_s))
        self.record_objects([first] if first is not None else [])
        now = self.clock.now_s()
        for key, alive in self.presence.changes():
            agent = agent_of_mec_token(key)
            if agent is not None and not self.core.on_presence(agent, alive):
                self.counters.inc("ignored/presence_unknown_agent")
        for _key, alive in self.vehicles_presence.changes():
            if not alive:
                forgotten = self.core.vehicles_left()
                self.counters.inc("vehicles/forgotten_on_leave", forgotten)
                log.warning("the vehicles' process left the bus: %d vehicles' plans ended", forgotten)
        for item in self.acks.drain():
            vehicle = ACKS.id_of(item.key, "vehicle")
            if self.shard is not None and not self.core.owns_vehicle(vehicle):
                self.counters.inc("acks/other_shard")  # every shard hears every vehicle's acks
                continue
            for counter in self.core.receive_ack(vehicle, item.message, now):
                self.counters.inc(counter)

    def record_objects(self, items: list[Received] | None = None) -> None:
        """Keep the latest lists of `items` and of everything queued. Also called by the route handler
        (Zenoh thread) so a plan includes every list that reached the process before the request."""
        now = self.clock.now_s()
        for item in (items or []) + self.objects.drain():
            agent = OBJECTS.id_of(item.key, "agent")  # the key, not the payload, says who published
            stamp_ns, epoch = item.header.stamp.ToNanoseconds(), item.header.epoch
            if not self.core.receive_objects(agent, item.message, stamp_ns, now, epoch):
                self.counters.inc("rejected/unknown_agent")

    def publish_map(self, now: float) -> int:
        """Publish the maps; returns their data stamp (ns)."""
        start_ns = time.time_ns()
        msg, stamp_ns = self.core.map_message(now)
        stage = processing_stamp(f"{STAGE}/map", start_ns, time.time_ns())
        self.map_pub.put(msg, stamp_ns=stamp_ns or start_ns, frame_id="world", stages=[stage])
        self.counters.inc("maps/published")
        return stamp_ns or start_ns

    def push(self, now: float) -> None:
        if self.node.uplink.cut_off():  # a send now goes nowhere: not an attempt, resent once back
            return
        given_up = self.core.plans_given_up
        for plan, stamp_ns, first_send in self.core.due(now):
            pub = self.node.publisher("route_plan", vehicle=plan.vehicle_id)  # declared once per vehicle
            pub.put(self.signer.sign(plan), stamp_ns=stamp_ns or time.time_ns(), frame_id="world")
            self.counters.inc("plans/pushed" if first_send else "plans/resent")
        if self.core.plans_given_up > given_up:
            self.counters.inc("plans/given_up", self.core.plans_given_up - given_up)

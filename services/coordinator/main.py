"""Cloud coordinator: merges every agent's objects into traffic maps and plans routes for vehicles.

    python -m services.coordinator [--settings deploy/coordinator/coordinator.yaml]

Inputs: `rmmdet/@v1/<agent>/objects` (all agents), the MECs' presence tokens
(`rmmdet/@v1/<agent>/@alive/mec/<agent>`), and the vehicles' acknowledgements
(`rmmdet/@v1/vehicles/<vehicle>/plan_ack`). An agent is LIVE while its object lists are fresh and its
MEC is present; only LIVE agents' objects enter the maps (shared/traffic/coverage.py).

Outputs:
- `rmmdet/@v1/cloud/maps/traffic` (TrafficMap) at `map_publish_hz`, and at once when an agent's
  coverage changes; the maps themselves are rebuilt when object lists arrive (at most
  `service.map_update_max_hz`) and before serving a plan if newer lists arrived since;
- the route RPC `rmmdet/@v1/cloud/@rpc/route/coordinator` (RouteRequest -> RouteResponse, errors as
  ErrorResponse): planned on the latest maps, carrying the agents that were missing;
- pushed plans on `rmmdet/@v1/cloud/plans/<vehicle>` every `replan_interval_s` for vehicles whose
  route can be improved by more than `replan_gain` or whose plan was made under another coverage,
  resent until acknowledged (`delivery.ack_timeout_s`, at most `delivery.max_sends` times).

Health is DEGRADED while an agent is not LIVE (the message names it). Header stamps of maps and plans
are the newest object list's stamp they derive from, so object -> plan latency can be measured.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import zenoh
from rmmdet.v1.common_pb2 import ErrorCode, ErrorResponse, Header
from rmmdet.v1.planning_pb2 import RouteAck, RouteRequest, RouteResponse

from shared.bus.codec import MessageDecoder, Rejected, RejectReason, encode
from shared.bus.health import DEGRADED, NOMINAL
from shared.bus.liveliness import LivelinessMonitor
from shared.bus.node import Node, Publisher, Received, processing_stamp
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.bus.streams import get_stream
from shared.scene.scene import Scene
from shared.service import run_service
from shared.shutdown import GracefulShutdown
from shared.timebase import SimTime
from shared.traffic.config import DEFAULT_COORDINATOR_CONFIG, CoordinatorSettings, load_coordinator_settings
from shared.traffic.core import CoordinatorCore, RequestRejected
from shared.traffic.coverage import AgentState
from shared.traffic.messages import agent_objects
from shared.traffic.plans import Ack

log = logging.getLogger("services.coordinator")

SERVICE, INSTANCE, SCOPE = "coordinator", "cloud", "cloud"  # INSTANCE: the --instance default
STAGE = "coordinator"
#: Longest idle wait of the main loop: presence changes are picked up at least this often.
POLL_S = 0.05
PRESENCE_QUEUE = 256
ACK_STATUS = {a.value: a for a in Ack}


def agent_of_key(key: str) -> str:
    """`agent1` from `rmmdet/@v1/agent1/objects` (the key, not the payload, says who published)."""
    return (get_stream("objects").ids(key) or {}).get("agent", "")


def vehicle_of_ack_key(key: str) -> str:
    """`v01` from `rmmdet/@v1/vehicles/v01/plan_ack`."""
    return (get_stream("route_ack").ids(key) or {}).get("vehicle", "")


def mec_of_token(key: str) -> str | None:
    """The agent of a MEC presence token `rmmdet/@v1/<agent>/@alive/mec/<agent>`, None otherwise."""
    ids = get_stream("alive").ids(key)
    if ids is None or ids["service"] != "mec" or ids["scope"] != ids["instance"]:
        return None
    return ids["instance"]


class RouteRpc:
    """The route queryable's handler. Runs on a Zenoh thread: decode, plan (the core's lock guards the
    state), reply; never raises, never blocks beyond the planning itself."""

    def __init__(
        self, node: Node, core: CoordinatorCore, before_plan: Callable[[], None], clock: SimTime
    ) -> None:
        self.node = node
        self.core = core
        self.before_plan = before_plan
        self.clock = clock
        self.stream = get_stream("route_rpc")
        self.key = self.stream.key()
        self.qos = self.stream.qos.publisher_kwargs()
        self.decoder = MessageDecoder(RouteRequest, node.counters)
        self._seq_lock = threading.Lock()
        self._seq = 0

    def __call__(self, query: zenoh.Query) -> None:
        start_ns = time.time_ns()
        counters = self.node.counters
        counters.inc("requests")
        try:
            if query.payload is None:
                raise Rejected(RejectReason.DECODE, "query without payload")
            attachment = query.attachment.to_bytes() if query.attachment is not None else None
            decoded = self.decoder.decode_or_raise(query.payload.to_bytes(), str(query.encoding), attachment)
            self.before_plan()
            plan, stamp_ns = self.core.serve(decoded.message, self.clock.now_s(), start_ns)
        except Rejected as err:
            counters.inc(f"rejected/{err.reason}")
            self._error(query, ErrorCode.ERROR_CODE_INVALID_REQUEST, str(err))
            return
        except RequestRejected as err:
            counters.inc(f"rejected/{err.reason}")
            self._error(query, err.code, err.message)
            return
        with self._seq_lock:
            self._seq += 1
            seq = self._seq
        header = Header(source_id=self.node.source_id, seq=seq, frame_id="world")
        header.stamp.FromNanoseconds(stamp_ns or start_ns)
        header.processing.append(processing_stamp(f"{STAGE}/plan", start_ns, time.time_ns()))
        plan.header.CopyFrom(header)
        # RouteResponse has no header field: the codec puts the header in the attachment.
        encoded = encode(RouteResponse(plan=plan), header)
        query.reply(
            self.key, encoded.payload, encoding=encoded.encoding, attachment=encoded.attachment, **self.qos
        )
        counters.inc("plans/served")

    def _error(self, query: zenoh.Query, code: ErrorCode.ValueType, message: str) -> None:
        encoded = encode(ErrorResponse(code=code, message=message))
        query.reply_err(encoded.payload, encoding=encoded.encoding)


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    settings = load_coordinator_settings(args.settings)
    scene = Scene.load(settings.scene)
    core = CoordinatorCore(scene, settings, settings.service.max_vehicles)
    with Node(conf, service=SERVICE, instance=args.instance, scope=SCOPE, stop=shutdown.event) as node:
        # Coverage, map smoothing and plan timing run on the clock of record (sim time when a sim runs).
        clock = SimTime()
        node.follow_sim_time(clock)
        service = CoordinatorService(node, core, settings, clock)
        monitor = LivelinessMonitor(
            node.session, get_stream("alive").pattern(service="mec"), on_change=service.on_presence
        )
        try:
            node.queryable(get_stream("route_rpc").key(), RouteRpc(node, core, service.record_objects, clock))
            log.info(
                "coordinator up: scene %s, agents %s, policy %s, maps %.1f Hz, replan every %.1f s",
                scene.scene_id,
                core.agents,
                settings.planner.policy,
                settings.map_publish_hz,
                settings.replan_interval_s,
            )
            service.run(shutdown)
        finally:
            monitor.undeclare()
        log.info("counters at exit: %s", node.counters.snapshot())
    return 0


class CoordinatorService:
    """The main loop: ingest objects, presence and acks; rebuild and publish maps; push plans."""

    def __init__(
        self, node: Node, core: CoordinatorCore, settings: CoordinatorSettings, clock: SimTime
    ) -> None:
        self.node = node
        self.core = core
        self.settings = settings
        self.clock = clock
        self.counters = node.counters
        # Object lists older than the stale threshold on arrival would not make their agent LIVE.
        self.objects = node.subscribe_stream(
            "objects",
            maxsize=settings.service.objects_queue_per_agent * len(core.agents),
            max_age_s=settings.coverage.stale_after_s,
            clock_s=clock.now_s,
        )
        self.acks = node.subscribe_stream("route_ack")
        self.map_pub = node.publisher("traffic_map")
        self.plan_pubs: dict[str, Publisher] = {}  # one per vehicle, declared once (declare churn leaks)
        self.presence: BoundedQueue[tuple[str, bool]] = BoundedQueue(
            PRESENCE_QUEUE, OverflowPolicy.DROP_OLDEST
        )
        self.states = dict.fromkeys(core.agents, AgentState.LOST)
        self.active_plans = 0
        node.health.set_status(self.health)

    def on_presence(self, key: str, alive: bool) -> None:
        """Liveliness callback (Zenoh thread): enqueue only."""
        agent = mec_of_token(key)
        if agent is not None:
            self.presence.put((agent, alive))

    def health(self) -> tuple[int, str]:
        """Health status (Zenoh thread): reads the main loop's cached values only."""
        states = self.states
        missing = [f"{a} {s.value}" for a, s in states.items() if s is not AgentState.LIVE]
        text = f"{len(states) - len(missing)}/{len(states)} agents LIVE, {self.active_plans} active plans"
        return (DEGRADED, f"{text}; missing: {', '.join(missing)}") if missing else (NOMINAL, text)

    def run(self, shutdown: GracefulShutdown) -> None:
        settings = self.settings
        map_period_s = 1.0 / settings.map_publish_hz
        min_update_s = 1.0 / settings.service.map_update_max_hz
        now = self.clock.now_s()
        next_map_s = now
        next_log_s = now + settings.report_interval_s
        last_update_s = -math.inf
        while not shutdown.requested:
            wait_s = min(POLL_S, next_map_s - self.clock.now_s())
            self.ingest(wait_s)
            now = self.clock.now_s()
            changed = self.check_coverage(now)
            if changed or now >= next_map_s or (self.core.dirty and now - last_update_s >= min_update_s):
                self.core.update_map(now)
                last_update_s = now
            if changed or now >= next_map_s:
                self.publish_map(now)
                next_map_s = now + map_period_s  # a coverage-change publish restarts the period
            issued = self.core.replan_if_due(now, time.time_ns())
            if issued is not None:
                if issued:
                    log.info("replan: %d plans to push", issued)
                self.active_plans = self.core.active_plans(now)
            self.push(now)
            if now >= next_log_s:
                next_log_s = now + settings.report_interval_s
                log.info(
                    "coverage %s; %d active plans; counters %s",
                    {a: s.value for a, s in self.states.items()},
                    self.core.active_plans(now),
                    self.counters.snapshot(),
                )

    def ingest(self, wait_s: float) -> None:
        """Wait up to `wait_s` for object lists, then take everything queued."""
        first = self.objects.recv(timeout=max(0.0, wait_s))
        self.record_objects([first] if first is not None else [])
        for agent, alive in self.presence.drain():
            if not self.core.on_presence(agent, alive):
                self.counters.inc("ignored/presence_unknown_agent")
        for item in self.acks.drain():
            self.on_ack(item)

    def record_objects(self, items: list[Received] | None = None) -> None:
        """Keep the latest lists of `items` and of everything queued. Also called by the route handler
        (Zenoh thread) so a plan includes every list that reached the process before the request."""
        items = (items or []) + self.objects.drain()
        now = self.clock.now_s()
        min_existence = self.settings.maps.min_existence_probability
        for item in items:
            agent = agent_of_key(item.key)
            objs = agent_objects(agent, item.message, min_existence)
            if not self.core.on_objects(agent, objs, item.header.stamp.ToNanoseconds(), now):
                self.counters.inc("rejected/unknown_agent")

    def check_coverage(self, now: float) -> bool:
        states = self.core.states(now)
        if states == self.states:
            return False
        log.warning("coverage: %s", ", ".join(f"{a} {s.value}" for a, s in states.items()))
        self.states = states
        return True

    def publish_map(self, now: float) -> None:
        start_ns = time.time_ns()
        msg, stamp_ns = self.core.map_message(now)
        stage = processing_stamp(f"{STAGE}/map", start_ns, time.time_ns())
        self.map_pub.put(msg, stamp_ns=stamp_ns or start_ns, frame_id="world", stages=[stage])
        self.counters.inc("maps/published")

    def push(self, now: float) -> None:
        given_up = self.core.plans_given_up
        due = self.core.due(now)
        if self.core.plans_given_up > given_up:
            self.counters.inc("plans/given_up", self.core.plans_given_up - given_up)
        for plan, stamp_ns, first_send in due:
            pub = self.plan_pubs.get(plan.vehicle_id)
            if pub is None:
                pub = self.plan_pubs[plan.vehicle_id] = self.node.publisher(
                    "route_plan", vehicle=plan.vehicle_id
                )
            pub.put(plan, stamp_ns=stamp_ns or time.time_ns(), frame_id="world")
            self.counters.inc("plans/pushed" if first_send else "plans/resent")

    def on_ack(self, item: Received) -> None:
        ack: RouteAck = item.message
        vehicle = vehicle_of_ack_key(item.key)
        if ack.vehicle_id != vehicle:
            self.counters.inc("rejected/ack_vehicle_mismatch")
            return
        status = ACK_STATUS.get(ack.status)
        if status is None:
            self.counters.inc("rejected/ack_status")
            return
        self.counters.inc(f"acks/{status.name.lower()}")
        if not self.core.on_ack(vehicle, ack.plan_id, int(ack.version), status):
            self.counters.inc("acks/not_latest")


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--settings", type=Path, default=DEFAULT_COORDINATOR_CONFIG, help="coordinator settings YAML"
    )


def cli(argv: list[str] | None = None) -> int:
    return run_service(
        SERVICE,
        main,
        description=__doc__ or "",
        add_args=add_args,
        default_instance=INSTANCE,
        argv=argv,
    )


if __name__ == "__main__":
    sys.exit(cli())

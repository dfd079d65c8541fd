"""Client-side helpers for tests and benchmarks of the coordinator: route RPC calls, its health report,
and a recorder of the traffic maps it publishes."""

from __future__ import annotations

import subprocess
import threading
import time
from dataclasses import dataclass, field

import zenoh
from google.protobuf.message import DecodeError
from rmmdet.v1.common_pb2 import ErrorResponse
from rmmdet.v1.health_pb2 import ServiceHealth
from rmmdet.v1.planning_pb2 import RoutePlan, RouteRequest, RouteResponse
from rmmdet.v1.traffic_pb2 import AgentState

from shared.bus.codec import encode
from shared.bus.node import Node, Subscription
from shared.bus.streams import get_stream
from tests.helpers import spawn

RPC_TIMEOUT_S = 2.0
STATE_NAMES = {AgentState.AGENT_STATE_LIVE: "LIVE", AgentState.AGENT_STATE_STALE: "STALE"}
STATE_NAMES[AgentState.AGENT_STATE_LOST] = "LOST"


class RouteClient:
    """Blocking route requests, one querier per vehicle id (tests only; vehicles use non-blocking gets).
    Like a vehicle it asks every server on the key (a sharded coordinator's shards) and takes a plan
    over an error; `source` tells which process answered (the reply header's source id)."""

    def __init__(self, node: Node, source_id: str = "test/route-client") -> None:
        self.session = node.session
        self.queriers: dict[str, zenoh.Querier] = {}
        self.source_id = source_id
        self.seq = 0

    def querier(self, vehicle_id: str) -> zenoh.Querier:
        if vehicle_id not in self.queriers:
            key = get_stream("route_rpc").key(vehicle=vehicle_id)
            self.queriers[vehicle_id] = self.session.declare_querier(
                key,
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=RPC_TIMEOUT_S,
            )
        return self.queriers[vehicle_id]

    def wait_ready(self, timeout_s: float, vehicle_id: str = "v01") -> None:
        deadline = time.monotonic() + timeout_s
        while not getattr(self.querier(vehicle_id).matching_status, "matching", False):
            if time.monotonic() > deadline:
                raise TimeoutError("no route queryable")
            time.sleep(0.05)

    def request(
        self, vehicle_id: str, lane: str, destination: str, version: int = 0
    ) -> RoutePlan | ErrorResponse | None:
        """The plan, the error reply, or None when nobody answered."""
        self.seq += 1
        req = RouteRequest(
            vehicle_id=vehicle_id,
            current_lane_id=lane,
            destination_junction_id=destination,
            current_plan_version=version,
        )
        req.header.source_id = self.source_id
        req.header.seq = self.seq
        req.header.stamp.FromNanoseconds(time.time_ns())
        encoded = encode(req)
        first_error: ErrorResponse | None = None
        for reply in self.querier(vehicle_id).get(payload=encoded.payload, encoding=encoded.encoding):
            if reply.ok is not None:
                response = RouteResponse()
                response.ParseFromString(reply.ok.payload.to_bytes())
                return response.plan
            if first_error is None:
                error = ErrorResponse()
                try:
                    error.ParseFromString(reply.err.payload.to_bytes() if reply.err is not None else b"")
                except DecodeError:  # Zenoh's own error (b"Timeout"): nobody answered in time
                    continue
                first_error = error
        return first_error

    def close(self) -> None:
        for querier in self.queriers.values():
            querier.undeclare()


def coordinator_health(
    session: zenoh.Session, timeout_s: float = 2.0, instance: str = "cloud"
) -> ServiceHealth | None:
    key = get_stream("health").key(scope="cloud", service="coordinator", instance=instance)
    for reply in session.get(key, timeout=timeout_s):
        if reply.ok is not None:
            report = ServiceHealth()
            report.ParseFromString(reply.ok.payload.to_bytes())
            return report
    return None


def counters(report: ServiceHealth) -> dict[str, int]:
    return {c.name: c.value for c in report.counters}


def coordinator_counters(session: zenoh.Session) -> dict[str, int]:
    """The coordinator's counters now; none while it does not answer."""
    report = coordinator_health(session)
    return counters(report) if report is not None else {}


@dataclass
class MapLog:
    """Traffic maps received: (monotonic arrival, {agent: LIVE/STALE/LOST})."""

    rows: list[tuple[float, dict[str, str]]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def consume(self, sub: Subscription, done: threading.Event, merge: bool = False) -> None:
        """`merge`: maps of several publishers (a sharded coordinator's regions, each with its own
        agents): each row is every publisher's latest coverage together."""
        latest: dict[str, dict[str, str]] = {}
        while not done.is_set():
            item = sub.recv(timeout=0.1)
            if item is not None:
                states = {c.agent_id: STATE_NAMES.get(c.state, "?") for c in item.message.coverage}
                if merge:
                    latest[item.key] = states
                    states = {a: s for per_key in latest.values() for a, s in per_key.items()}
                with self.lock:
                    self.rows.append((time.monotonic(), states))

    def since(self, t: float) -> list[tuple[float, dict[str, str]]]:
        with self.lock:
            return [r for r in self.rows if r[0] >= t]

    def wait(self, pred, timeout_s: float, since: float) -> float:
        """Arrival of the first map after `since` whose coverage satisfies `pred`."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for t, states in self.since(since):
                if pred(states):
                    return t
            time.sleep(0.02)
        last = self.since(since)[-1:]
        raise AssertionError(f"no such map within {timeout_s} s (last: {last})")


def spawn_planning_loop(
    coordinator_args: list[str], sim_args: list[str], replan_interval_s: float = 0.5, vehicles: int = 10
) -> dict[str, subprocess.Popen]:
    """The coordinator (re-planning every `replan_interval_s`) and the sim at 1x with `vehicles` that ask
    for, follow and acknowledge plans; each with its own connect flags (e.g. through a delayed link)."""
    return {
        "coordinator": spawn(
            ["-m", "services.coordinator", *coordinator_args],
            env={"RMMDET_COORD_REPLAN_INTERVAL_S": str(replan_interval_s)},
        ),
        "sim": spawn(
            ["-m", "services.sim", "--speed", "1", "--vehicles", str(vehicles), *sim_args],
            env={"RMMDET_SIM_TRAFFIC__ROUTE_POLICY": "plan"},
        ),
    }

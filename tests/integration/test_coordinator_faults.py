"""Fault injection on the coordinator's inputs (docs/reliability.md R4): real processes — router,
coordinator, three stand-in MECs (tests/integration/fake_mec.py) publishing object lists at 15 Hz.

One MEC is killed with SIGKILL:
- the coordinator's TrafficMap marks that agent STALE (or LOST) within 1 s;
- maps keep coming, route requests are still answered, with the agent in `coverage.missing_agents`;
- its health report is DEGRADED and names the agent;
then the MEC is restarted: LIVE again within 1 s of its first new object list, plans no longer list it.
Time limits scale with RSP_TIME_SCALE (slow machines).
"""

from __future__ import annotations

import os
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
from rmmdet.v1.health_pb2 import HealthLevel
from rmmdet.v1.planning_pb2 import RoutePlan

from shared.bus import names
from shared.bus.liveliness import alive_tokens
from shared.bus.node import Node
from shared.bus.streams import get_stream
from tests.helpers import Router, spawn, stop, wait_until
from tests.integration.coordinator_client import MapLog, RouteClient, coordinator_health, counters

pytestmark = [pytest.mark.integration, pytest.mark.fault, pytest.mark.timeout(120)]

SCALE = float(os.environ.get("RSP_TIME_SCALE", "1"))
AGENTS = ("agent1", "agent2", "agent3")
VICTIM = "agent2"
STARTUP_S = 45.0
STALE_WITHIN_S = 1.0 * SCALE
LIVE_WITHIN_S = 1.0 * SCALE
WINDOW_S = 2.0
MAP_HZ = 2.0  # coordinator.yaml map_publish_hz
MIN_MAP_FRACTION = 0.75


@dataclass
class Cluster:
    router: Router
    procs: dict[str, subprocess.Popen]
    node: Node
    maps: MapLog
    routes: RouteClient
    victim_first: list[float]  # arrival times of the victim's object lists at the test's subscriber

    def start_mec(self, agent: str) -> None:
        self.procs[agent] = spawn(
            ["-m", "tests.integration.fake_mec", "--instance", agent, *self.router.client_args()]
        )

    def plan(self) -> RoutePlan:
        reply = self.routes.request("t01", "l0", "j3")
        assert isinstance(reply, RoutePlan), f"no plan: {reply}"
        return reply


@pytest.fixture
def cluster(router: Router) -> Iterator[Cluster]:
    procs = {"coordinator": spawn(["-m", "services.coordinator", *router.client_args()])}
    node = Node(router.client_config(), service="test", instance="coordinator-faults", scope="site")
    node.open()
    done = threading.Event()
    threads: list[threading.Thread] = []
    try:
        cluster = Cluster(router, procs, node, MapLog(), RouteClient(node), [])
        for agent in AGENTS:
            cluster.start_mec(agent)
        maps = node.subscribe_stream("traffic_map", maxsize=1000)
        victim = node.subscribe_stream("objects", agent=VICTIM, maxsize=1000)

        def consume_victim() -> None:
            while not done.is_set():
                if victim.recv(timeout=0.1) is not None:
                    cluster.victim_first.append(time.monotonic())

        threads = [
            threading.Thread(target=cluster.maps.consume, args=(maps, done), daemon=True),
            threading.Thread(target=consume_victim, daemon=True),
        ]
        for t in threads:
            t.start()
        yield cluster
    finally:
        done.set()
        for t in threads:
            t.join(2)
        node.close()
        for p in procs.values():
            stop(p)


def all_live(states: dict[str, str]) -> bool:
    return all(states.get(a) == "LIVE" for a in AGENTS)


def test_mec_kill_marks_agent_missing_and_restart_recovers(cluster: Cluster) -> None:
    maps = cluster.maps
    maps.wait(all_live, STARTUP_S, since=time.monotonic())
    cluster.routes.wait_ready(STARTUP_S)
    assert list(cluster.plan().coverage.missing_agents) == []

    cluster.procs[VICTIM].send_signal(signal.SIGKILL)
    cluster.procs[VICTIM].wait(5)
    t_kill = time.monotonic()
    t_stale = maps.wait(lambda s: s.get(VICTIM) in ("STALE", "LOST"), 5.0 * SCALE, since=t_kill)
    assert t_stale - t_kill <= STALE_WITHIN_S, f"{VICTIM} missing after {t_stale - t_kill:.3f} s"
    assert all(maps.since(t_stale)[-1][1][a] == "LIVE" for a in AGENTS if a != VICTIM)

    # The coordinator keeps serving and publishing, with the agent flagged missing.
    t_window = time.monotonic()
    while time.monotonic() < t_window + WINDOW_S:
        plan = cluster.plan()
        assert list(plan.coverage.missing_agents) == [VICTIM]
        assert VICTIM not in plan.coverage.live_agents
        time.sleep(0.2)
    published = maps.since(t_window)
    assert len(published) >= MIN_MAP_FRACTION * MAP_HZ * WINDOW_S, f"{len(published)} maps in {WINDOW_S} s"
    assert all(states[VICTIM] != "LIVE" for _, states in published)
    report = coordinator_health(cluster.node.session)
    assert report is not None and report.level == HealthLevel.HEALTH_LEVEL_DEGRADED
    assert VICTIM in report.message
    assert counters(report)["plans/served"] >= 1

    t_restart = time.monotonic()
    cluster.start_mec(VICTIM)
    deadline = t_restart + STARTUP_S
    while not [t for t in cluster.victim_first if t >= t_restart]:
        assert time.monotonic() < deadline, f"{VICTIM} did not come back"
        time.sleep(0.05)
    t_first = min(t for t in cluster.victim_first if t >= t_restart)
    t_live = maps.wait(all_live, 5.0 * SCALE, since=t_restart)
    assert t_live - t_first <= LIVE_WITHIN_S, f"LIVE {t_live - t_first:.3f} s after the first list"
    assert list(cluster.plan().coverage.missing_agents) == []
    report = coordinator_health(cluster.node.session)
    assert report is not None and report.level == HealthLevel.HEALTH_LEVEL_NOMINAL


def test_served_plans_are_copied_for_viewers_only_while_watched(cluster: Cluster) -> None:
    """A plan a vehicle asks for is copied on `route_plan_served` (the live view draws it) only while
    something subscribes there: not before, not after it leaves."""
    cluster.maps.wait(all_live, STARTUP_S, since=time.monotonic())
    cluster.routes.wait_ready(STARTUP_S)
    cluster.plan()
    report = coordinator_health(cluster.node.session)
    assert report is not None and counters(report).get("plans/copied", 0) == 0
    copies = cluster.node.subscribe_stream("route_plan_served", maxsize=10)
    deadline = time.monotonic() + 5.0 * SCALE
    reply = cluster.plan()
    while (item := copies.recv(timeout=0.2)) is None:  # until the subscription has reached it
        assert time.monotonic() < deadline, "no copy of a served plan"
        reply = cluster.plan()
    assert item.message.vehicle_id == reply.vehicle_id == "t01"
    assert 0 < item.message.version <= reply.version  # a copy may trail the newest reply by one
    copies.undeclare()
    time.sleep(1.0 * SCALE)  # the coordinator learns that nothing matches any more
    report = coordinator_health(cluster.node.session)
    assert report is not None
    before = counters(report)["plans/copied"]
    cluster.plan()
    report = coordinator_health(cluster.node.session)
    assert report is not None and counters(report)["plans/copied"] == before, "copied with nobody watching"


def test_a_present_coordinator_answers_at_once(router: Router) -> None:
    """The coordinator's presence token tells every vehicle to ask now (a restarted coordinator serves
    them all at once, reliability R3), so it is declared only once the route RPC answers: requests sent
    the moment the token appears all get a plan. With the token declared at the session's opening,
    most of them found no queryable yet and went unanswered (the sim papered over it with a 0.3 s wait,
    too short on a busy host)."""
    alive = get_stream("alive").pattern(scope="cloud", service=names.COORDINATOR)
    with Node(router.client_config(), service="test", instance="first-ask", scope="site") as node:
        for trial in range(3):
            coordinator = spawn(["-m", "services.coordinator", *router.client_args()])
            try:
                wait_until(lambda: bool(alive_tokens(node.session, alive, timeout_s=0.2)), STARTUP_S, "token")
                replies: dict[str, object] = {}

                def ask(vehicle: str, replies: dict[str, object] = replies) -> None:
                    replies[vehicle] = RouteClient(node, f"test/{vehicle}").request(vehicle, "l0", "j3")

                askers = [threading.Thread(target=ask, args=(f"v{i:02d}",)) for i in range(10)]
                for t in askers:
                    t.start()
                for t in askers:
                    t.join()
            finally:
                stop(coordinator)
            unanswered = sorted(v for v, reply in replies.items() if not isinstance(reply, RoutePlan))
            assert not unanswered, f"trial {trial}: asked at the token, not planned: {unanswered}"

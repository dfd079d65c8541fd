"""Router restart and freeze (docs/reliability.md R1, R2): SIGKILL the Zenoh router under a running loop
and start it again 2 s later on the same endpoint; or SIGSTOP it for 5 s (alive to TCP, forwarding
nothing: the clients' transports stay open, so none knows it is cut off) and SIGCONT it.

The loop: router, coordinator (re-planning every 0.5 s), the sim at 1x with 10 vehicles asking for and
following plans, and a stand-in MEC per agent (object lists at 10 Hz, the MEC's presence token). The
last agent's MEC comes up just before the kill: the coverage change makes the coordinator push new
plans, whose delivery and acknowledgements cross the outage. Every client is cut off at once; each
knows it (its transports close: `shared/bus/uplink.py`) and does not blame the others. Asserted:
- no service exits; object lists of every agent flow again within 3 s of the restart (or SIGCONT);
- no agent is ever LOST and the coverage never changes in any map (no flips from the blip: the
  coordinator holds coverage while cut off and for a grace after, presence leaves are held);
- 0 plans given up (sends while cut off are not attempts), every pushed plan the test saw acked,
  none accepted twice (a plan delivered again is acknowledged DUPLICATE, not run again).
Time limits scale with RSP_TIME_SCALE (slow machines).
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections import Counter
from collections.abc import Iterator

import pytest
from rmmdet.v1.planning_pb2 import ACK_STATUS_ACCEPTED

from shared.bus.node import Node
from tests.helpers import Router, spawn, start_router, stop
from tests.integration.coordinator_client import MapLog, coordinator_health, counters, spawn_planning_loop

pytestmark = [pytest.mark.integration, pytest.mark.fault, pytest.mark.timeout(180)]

SCALE = float(os.environ.get("RSP_TIME_SCALE", "1"))
AGENTS = ("agent1", "agent2", "agent3")
DOWN_S = 2.0  # the router is away this long (R1)
FROZEN_S = 5.0  # ... or stopped this long (R2)
FLOWING_WITHIN_S = 3.0 * SCALE  # object lists again, after the restart or SIGCONT
AFTER_S = 8.0  # watched after the restart
STARTUP_S = 60.0


class Seen:
    """What the test's own subscriptions saw: object lists per agent, pushed plans and acks."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.objects: dict[str, list[float]] = {a: [] for a in AGENTS}
        self.pushed: set[str] = set()
        self.acked: set[str] = set()
        self.accepted: Counter[tuple[str, int]] = Counter()  # ACCEPTED acks per plan id and version


@pytest.fixture
def system() -> Iterator[tuple[Router, dict, Node, MapLog, Seen]]:
    router = start_router()
    procs = spawn_planning_loop(router.client_args(), router.client_args())
    for agent in AGENTS[:-1]:  # the last one comes up in the test, just before the fault
        procs[agent] = fake_mec(router, agent)
    node = Node(router.client_config(), service="test", instance="router-restart", scope="site")
    node.open()
    maps, seen, done = MapLog(), Seen(), threading.Event()
    objects = node.subscribe_stream("objects", maxsize=10_000)
    plans = node.subscribe_stream("route_plan", maxsize=10_000)
    acks = node.subscribe_stream("route_ack", maxsize=10_000)

    def consume() -> None:
        while not done.is_set():
            for item in objects.drain():
                with seen.lock:
                    seen.objects[item.key.split("/")[2]].append(time.monotonic())
            for item in plans.drain():
                with seen.lock:
                    seen.pushed.add(item.message.plan_id)
            for item in acks.drain():
                with seen.lock:
                    seen.acked.add(item.message.plan_id)
                    if item.message.status == ACK_STATUS_ACCEPTED:
                        seen.accepted[item.message.plan_id, item.message.version] += 1
            time.sleep(0.02)

    threads = [
        threading.Thread(target=consume, daemon=True),
        threading.Thread(
            target=maps.consume, args=(node.subscribe_stream("traffic_map", maxsize=10_000), done)
        ),
    ]
    for t in threads:
        t.start()
    box = {"router": router}
    try:
        yield box["router"], procs, node, maps, seen
    finally:
        done.set()
        for t in threads:
            t.join(2)
        node.close()
        for p in procs.values():
            stop(p)
        stop(box["router"].proc)


def coordinator_counters(node: Node) -> dict[str, int]:
    report = coordinator_health(node.session)
    assert report is not None, "the coordinator did not answer its health query"
    return counters(report)


def fake_mec(router: Router, agent: str):
    return spawn(
        ["-m", "tests.integration.fake_mec", "--instance", agent, "--rate-hz", "10", *router.client_args()]
    )


def flips(rows: list[tuple[float, dict[str, str]]]) -> dict[str, list[str]]:
    """Each agent's coverage states in order, repeats collapsed."""
    out: dict[str, list[str]] = {a: [] for a in AGENTS}
    for _, states in rows:
        for agent in AGENTS:
            state = states.get(agent, "?")
            if not out[agent] or out[agent][-1] != state:
                out[agent].append(state)
    return out


def test_a_router_restart_loses_nothing_and_flips_nothing(system) -> None:
    check_router_fault(system, "R1")


def test_a_router_freeze_loses_nothing_and_flips_nothing(system) -> None:
    check_router_fault(system, "R2")


def check_router_fault(system, fault: str) -> None:
    """R1: SIGKILL the router, a new one DOWN_S later; R2: SIGSTOP it FROZEN_S, then SIGCONT."""
    router, procs, node, maps, seen = system
    t0 = time.monotonic()
    maps.wait(lambda s: all(s.get(a) == "LIVE" for a in AGENTS[:-1]), STARTUP_S, since=t0)
    deadline = time.monotonic() + STARTUP_S
    while not seen.acked:  # vehicles ask for plans, follow and acknowledge them
        assert time.monotonic() < deadline, "no plan acknowledged before the fault"
        time.sleep(0.1)
    procs[AGENTS[-1]] = fake_mec(router, AGENTS[-1])  # coverage changes: plans are pushed
    maps.wait(lambda s: all(s.get(a) == "LIVE" for a in AGENTS), STARTUP_S, since=t0)
    while not seen.pushed:
        assert time.monotonic() < deadline, f"no plan pushed before the fault: {coordinator_counters(node)}"
        time.sleep(0.05)
    t_kill = time.monotonic()
    if fault == "R1":
        router.proc.send_signal(signal.SIGKILL)
        router.proc.wait(5)
        time.sleep(DOWN_S)
        restarted = start_router(router.port)
        router.proc = restarted.proc  # the fixture stops this one
    else:
        router.proc.send_signal(signal.SIGSTOP)
        try:
            time.sleep(FROZEN_S)
        finally:
            router.proc.send_signal(signal.SIGCONT)
    t_back = time.monotonic()
    time.sleep(AFTER_S)

    exited = {name: p.returncode for name, p in procs.items() if p.poll() is not None}
    assert not exited, f"services exited: {exited}"
    with seen.lock:
        resumed = {a: next((t for t in ts if t >= t_back), None) for a, ts in seen.objects.items()}
    late = {a: None if t is None else round(t - t_back, 3) for a, t in resumed.items()}
    print(
        f"{fault}: object lists again {late} s after the {'restart' if fault == 'R1' else 'SIGCONT'} "
        f"(router back {t_back - t_kill:.2f} s after the fault)"
    )
    assert all(t is not None and t - t_back <= FLOWING_WITHIN_S for t in resumed.values()), late

    rows = maps.since(t_kill)
    assert any(r[0] >= t_back for r in rows), "no traffic map after the restart"
    states = flips(rows)
    print(f"{fault}: coverage in the maps around the fault: {states}")
    assert all(s == ["LIVE"] for s in states.values()), f"coverage flipped: {states}"

    c = coordinator_counters(node)
    with seen.lock:
        unacked = seen.pushed - seen.acked
    print(
        f"{fault}: coordinator plans pushed {c.get('plans/pushed', 0)}, resent {c.get('plans/resent', 0)}, "
        f"given up {c.get('plans/given_up', 0)}; pushed plans seen {len(seen.pushed)}, "
        f"unacknowledged {len(unacked)}"
    )
    assert c.get("plans/given_up", 0) == 0, c
    # A plan pushed in the last ack timeout may still be on its way back.
    time.sleep(1.0)
    with seen.lock:
        unacked = seen.pushed - seen.acked
    assert not unacked, f"pushed plans never acknowledged: {sorted(unacked)}"
    with seen.lock:
        twice = {p: n for p, n in seen.accepted.items() if n > 1}
    assert not twice, f"plans accepted more than once (a duplicate run): {twice}"

"""A delayed link (docs/reliability.md N3, 100 ms ± 20 ms each way; no `tc netem` here, so a TCP relay:
tests/integration/delay_relay.py): one agent's MEC and the vehicles (the sim) reach the router only
through it, the coordinator directly.

Asserted: the delayed agent stays LIVE in every map (its data is 0.1 s older, the stale limit 0.5 s);
its object lists arrive no sooner than the delay allows and within delay + jitter + 0.1 s at p95 (the
relay works, nothing piles up);
plans still reach the vehicles: every pushed plan is acknowledged, none given up; a plan's push ->
acknowledgement round trip (twice through the delayed link) stays within 2 x 120 ms + 250 ms at p95.
Time limits scale with RSP_TIME_SCALE (slow machines).
"""

from __future__ import annotations

import os
import threading
import time

import pytest

from shared.bus.node import Node
from tests.helpers import Router, free_port, spawn, stop, wait_until
from tests.integration.coordinator_client import (
    MapLog,
    coordinator_counters,
    coordinator_health,
    counters,
    spawn_planning_loop,
)
from tests.integration.delay_relay import DelayRelay

pytestmark = [pytest.mark.integration, pytest.mark.fault, pytest.mark.timeout(150)]

SCALE = float(os.environ.get("RSP_TIME_SCALE", "1"))
DELAY_S, JITTER_S = 0.1, 0.02
STARTUP_S = 60.0
VEHICLES = 10
WATCH_S = 15.0
ROUND_TRIP_P95_S = 2 * (DELAY_S + JITTER_S) + 0.25 * SCALE


def publish_wall_s(header) -> float | None:
    """Wall time of the publisher's own `<node>/publish` processing stamp (the last one), s."""
    stamps = [p for p in header.processing if p.stage.endswith("/publish")]
    return stamps[-1].start.ToNanoseconds() / 1e9 if stamps else None


def percentile(sorted_values: list[float], q: float) -> float:
    """The `q` quantile (nearest rank below) of sorted values; NaN for none."""
    return sorted_values[int(q * (len(sorted_values) - 1))] if sorted_values else float("nan")


def test_a_delayed_link_delivers_plans_and_keeps_the_agent_live(router: Router) -> None:
    relay_port = free_port()
    with DelayRelay(relay_port, "127.0.0.1", router.port, DELAY_S, JITTER_S) as relay:
        delayed = ["--connect", f"tcp/127.0.0.1:{relay_port}"]
        procs = {
            **spawn_planning_loop(router.client_args(), delayed, vehicles=VEHICLES),
            "agent1": spawn(
                ["-m", "tests.integration.fake_mec", "--instance", "agent1", "--rate-hz", "10", *delayed]
            ),
            "agent2": spawn(
                [
                    "-m",
                    "tests.integration.fake_mec",
                    "--instance",
                    "agent2",
                    "--rate-hz",
                    "10",
                    *router.client_args(),
                ]
            ),
        }
        maps, done = MapLog(), threading.Event()
        transit: list[float] = []
        pushed: dict[str, float] = {}  # plan id -> publish wall time
        acked: dict[str, float] = {}  # plan id -> ack arrival wall time
        try:
            with Node(router.client_config(), service="test", instance="delay", scope="site") as node:
                objects = node.subscribe_stream("objects", agent="agent1", maxsize=1000)
                plans = node.subscribe_stream("route_plan", maxsize=1000)
                acks = node.subscribe_stream("route_ack", maxsize=1000)
                thread = threading.Thread(
                    target=maps.consume, args=(node.subscribe_stream("traffic_map", maxsize=1000), done)
                )
                thread.start()

                def drain() -> None:
                    for item in objects.drain():
                        sent = publish_wall_s(item.header)
                        if sent is not None:
                            transit.append(item.received_wall_ns / 1e9 - sent)
                    for item in plans.drain():
                        sent = publish_wall_s(item.header)
                        if sent is not None:
                            pushed.setdefault(item.message.plan_id, sent)
                    for item in acks.drain():
                        acked.setdefault(item.message.plan_id, item.received_wall_ns / 1e9)

                t0 = time.monotonic()
                maps.wait(
                    lambda s: s.get("agent1") == "LIVE" and s.get("agent2") == "LIVE", STARTUP_S, since=t0
                )
                # Every vehicle follows a plan before agent3 comes (a slow sim start would otherwise leave
                # nothing to re-plan: its requests would already see agent3's coverage).
                wait_until(
                    lambda: coordinator_counters(node.session).get("acks/accepted", 0) >= VEHICLES,
                    STARTUP_S,
                    f"{VEHICLES} vehicles following plans",
                )
                # agent3 comes up: the coverage change makes the coordinator push plans over the delay
                procs["agent3"] = spawn(
                    [
                        "-m",
                        "tests.integration.fake_mec",
                        "--instance",
                        "agent3",
                        "--rate-hz",
                        "10",
                        *router.client_args(),
                    ]
                )
                maps.wait(lambda s: s.get("agent3") == "LIVE", STARTUP_S, since=t0)
                t_watch = time.monotonic()
                transit.clear()
                while time.monotonic() - t_watch < WATCH_S:
                    drain()
                    time.sleep(0.05)
                time.sleep(1.0)  # acknowledgements of the last pushes on their way back
                drain()
                c = counters(coordinator_health(node.session) or pytest.fail("no coordinator health"))
                done.set()
                thread.join(2)
        finally:
            for p in procs.values():
                stop(p)
        states = {s.get("agent1") for _, s in maps.since(t_watch)}
        rtt = sorted(acked[p] - pushed[p] for p in pushed if p in acked)
        transit.sort()
        unacked = set(pushed) - set(acked)
        transit_p95, p95 = percentile(transit, 0.95), percentile(rtt, 0.95)
        print(
            f"N3 delay {DELAY_S * 1e3:.0f} ± {JITTER_S * 1e3:.0f} ms: agent1 object transit p50 "
            f"{percentile(transit, 0.5) * 1e3:.0f} ms, p95 {transit_p95 * 1e3:.0f} ms (n={len(transit)}); "
            f"plans pushed {len(pushed)}, acknowledged {len(rtt)}, push -> ack p50 "
            f"{percentile(rtt, 0.5) * 1e3:.0f} ms, p95 {p95 * 1e3:.0f} ms; coordinator counters {c}; "
            f"relay {relay.connections} connections, {relay.bytes_relayed / 1e6:.1f} MB"
        )
    assert states == {"LIVE"}, f"the delayed agent left LIVE: {states}"
    assert transit and min(transit) >= DELAY_S - JITTER_S - 0.005, "the relay delays"
    # nothing piles up: at p95 the delay and jitter plus a busy host's scheduling
    assert transit_p95 <= DELAY_S + JITTER_S + 0.1 * SCALE, f"object transit p95 {transit_p95:.3f} s"
    assert pushed, "no plan pushed when agent3's coverage came"
    assert not unacked, f"pushed plans never acknowledged: {sorted(unacked)}"
    assert c.get("plans/given_up", 0) == 0, c
    assert p95 <= ROUND_TRIP_P95_S, f"push -> ack p95 {p95:.3f} s"

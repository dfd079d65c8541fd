"""Real processes on loopback: router + clients exchange messages, bad input is counted, processes
that crash, get killed or start before the router never hang anything."""

from __future__ import annotations

import json
import signal
import subprocess
import time

import pytest
from rmmdet.v1.perception_pb2 import TrackedObjects

from shared.bus.codec import encoding_for
from shared.bus.liveliness import LivelinessMonitor, alive_tokens
from shared.bus.node import Node
from shared.bus.session import open_session
from shared.bus.streams import get_stream
from tests.helpers import Router, free_port, spawn, start_router, stop, wait_until

pytestmark = [pytest.mark.integration, pytest.mark.timeout(60)]

PEER = ["-m", "tests.integration.bus_peer"]


def events(proc: subprocess.Popen, until: str, timeout_s: float = 15.0) -> list[dict]:
    """Read the peer's JSON events until one named `until` (or fail on timeout/exit)."""
    seen: list[dict] = []
    deadline = time.monotonic() + timeout_s
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            if proc.poll() is not None:
                raise AssertionError(f"peer exited with {proc.returncode}; events so far {seen}")
            continue
        if line.startswith("{"):
            seen.append(json.loads(line))
            if seen[-1]["event"] == until:
                return seen
    raise AssertionError(f"no {until!r} event within {timeout_s} s; events so far {seen}")


def test_two_clients_exchange_messages_through_the_router(router: Router) -> None:
    sub = spawn([*PEER, "sub", "--expect", "50", *router.client_args()])
    pub = None
    try:
        events(sub, "ready")
        pub = spawn([*PEER, "pub", "--count", "50", "--rate-hz", "100", *router.client_args()])
        got = events(sub, "done", timeout_s=20)
        received = [e["seq"] for e in got if e["event"] == "received"]
        assert received == list(range(1, 51))
        assert [e["track_id"] for e in got if e["event"] == "received"] == list(range(1, 51))
        assert sub.wait(10) == 0
        assert pub.wait(10) == 0
    finally:
        for p in (sub, pub):
            if p is not None:
                stop(p)


def test_malformed_oversized_and_nan_payloads_are_counted_not_raised(router: Router) -> None:
    sub = spawn([*PEER, "sub", "--max-payload-bytes", "100000", *router.client_args()])
    try:
        events(sub, "ready")
        key = get_stream("objects").key(agent="agent1")
        enc = encoding_for(TrackedObjects)
        nan = TrackedObjects(agent_id="agent1")
        nan.header.source_id, nan.header.seq = "test", 1
        nan.objects.add(track_id=1).box.center_m.x = float("nan")
        good = TrackedObjects(agent_id="agent1")
        good.header.source_id, good.header.seq = "test", 2
        good.objects.add(track_id=7, existence_probability=1.0)
        with open_session(router.client_config(), timeout_s=5) as session:
            pub = session.declare_publisher(key)
            deadline = time.monotonic() + 5
            while not pub.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.02)
            pub.put(b"\x0a\xff\xff\xff\xff\xff garbage", encoding=enc)  # decode
            pub.put(b"\x00" * 200_000, encoding=enc)  # oversize
            pub.put(nan.SerializeToString(), encoding=enc)  # non_finite
            pub.put(good.SerializeToString(), encoding="text/plain")  # encoding
            pub.put(good.SerializeToString(), encoding=enc)  # accepted
            got = events(sub, "received")
            assert (got[-1]["seq"], got[-1]["track_id"]) == (2, 7)
            counters = {}
            for reply in session.get("rmmdet/v1/agent1/@health/testpeer/**", timeout=3):
                from rmmdet.v1.health_pb2 import ServiceHealth

                health = ServiceHealth()
                health.ParseFromString(reply.ok.payload.to_bytes())
                counters = {c.name: c.value for c in health.counters}
            pub.undeclare()
        assert counters == {
            "accepted": 1,
            "rejected/decode": 1,
            "rejected/oversize": 1,
            "rejected/non_finite": 1,
            "rejected/encoding": 1,
        }
        assert sub.poll() is None, "subscriber must survive bad input"
    finally:
        assert stop(sub) == 0


def test_killed_client_is_seen_leaving_and_others_keep_working(router: Router) -> None:
    with open_session(router.client_config(), timeout_s=5) as session:
        alive = LivelinessMonitor(session, "rmmdet/v1/*/@alive/**", queue_changes=True)
        victim = spawn([*PEER, "sub", "--instance", "victim", *router.client_args()])
        survivor = spawn([*PEER, "sub", "--instance", "survivor", "--expect", "5", *router.client_args()])
        try:
            events(victim, "ready")
            events(survivor, "ready")
            victim_key = get_stream("alive").key(scope="agent1", service="testpeer", instance="victim")
            # The victim's token reaches this session through the router, maybe after its "ready".
            deadline = time.monotonic() + 5.0
            while not alive.is_alive(victim_key) and time.monotonic() < deadline:
                time.sleep(0.02)
            assert alive.is_alive(victim_key)
            t0 = time.monotonic()
            victim.send_signal(signal.SIGKILL)
            victim.wait(5)
            while alive.is_alive(victim_key) and time.monotonic() - t0 < 5:
                time.sleep(0.01)
            assert not alive.is_alive(victim_key), "liveliness DELETE expected after SIGKILL"
            assert time.monotonic() - t0 < 2.0
            # The same join and leave, queued for a service loop, in order.
            assert [c for c in alive.changes() if c[0] == victim_key] == [
                (victim_key, True),
                (victim_key, False),
            ]
            assert alive.changes() == []  # taken once
            pub = spawn([*PEER, "pub", "--count", "5", *router.client_args()])
            got = events(survivor, "done")
            assert sum(e["event"] == "received" for e in got) == 5
            assert router.proc.poll() is None
            assert stop(pub) == 0
        finally:
            alive.undeclare()
            stop(victim)
            stop(survivor)


def test_crash_inside_the_session_exits_promptly(router: Router) -> None:
    proc = spawn([*PEER, "sub", "--crash-after-s", "0.5", *router.client_args()])
    try:
        rc = proc.wait(timeout=15)
    finally:
        stop(proc)
    out = proc.stdout.read() if proc.stdout else ""
    assert rc != 0
    assert "injected crash" in out


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_graceful_stop_exits_zero_quickly(router: Router, sig: int) -> None:
    proc = spawn([*PEER, "sub", *router.client_args()])
    events(proc, "ready")
    t0 = time.monotonic()
    assert stop(proc, sig, timeout_s=5) == 0
    assert time.monotonic() - t0 < 3.0


def test_router_stops_cleanly_on_sigterm() -> None:
    r = start_router()
    t0 = time.monotonic()
    assert stop(r.proc, signal.SIGTERM) == 0
    assert time.monotonic() - t0 < 3.0


def test_client_started_before_the_router_connects_when_it_appears() -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    sub = spawn([*PEER, "sub", "--expect", "3", "--connect", endpoint])
    router = None
    pub = None
    try:
        time.sleep(1.5)
        assert sub.poll() is None, "a client must wait for the router, not exit"
        router = start_router(port)
        events(sub, "ready")
        pub = spawn([*PEER, "pub", "--count", "3", "--connect", endpoint])
        got = events(sub, "done")
        assert [e["seq"] for e in got if e["event"] == "received"] == [1, 2, 3]
    finally:
        for p in (pub, sub):
            if p is not None:
                stop(p)
        if router is not None:
            stop(router.proc)


def test_cli_health_and_topics_see_the_running_services(router: Router) -> None:
    # Publishing until stopped (60 s at most): the three CLI calls below start a Python process each
    # (~3 s apiece on a loaded 2-core host), and 400 messages (8 s) ran out before the last one.
    pub = spawn(
        [*PEER, "pub", "--instance", "pub", "--count", "3000", "--rate-hz", "50", *router.client_args()]
    )
    sub = spawn([*PEER, "sub", "--instance", "sub", *router.client_args()])
    try:
        events(sub, "ready")
        events(pub, "ready")
        health = spawn(["-m", "services.cli", "--connect", router.endpoint, "health", "--answering"])
        out, _ = health.communicate(timeout=20)
        assert health.returncode == 0, out
        for row in ("router", "testpeer │ pub", "testpeer │ sub"):
            assert row in out, out
        topics = spawn(
            ["-m", "services.cli", "--connect", router.endpoint, "topics", "--duration", "2", "--json"]
        )
        out, _ = topics.communicate(timeout=20)
        rows = {r["key"]: r for r in map(json.loads, (ln for ln in out.splitlines() if ln.startswith("{")))}
        row = rows["rmmdet/v1/agent1/objects"]
        assert row["schema"] == "rmmdet.v1.TrackedObjects"
        assert 30 <= row["rate_hz"] <= 60, row
        assert (row["decode_errors"], row["gaps"]) == (0, 0)
        table = spawn(["-m", "services.cli", "--connect", router.endpoint, "topics", "--duration", "1"])
        out, _ = table.communicate(timeout=20)
        assert "rmmdet/v1/agent1/objects" in out, out
    finally:
        stop(pub)
        stop(sub)


def test_zenoh_session_to_missing_router_fails_cleanly() -> None:
    from shared.bus.session import SessionUnavailable
    from shared.bus.zenoh_config import DEFAULT_CLIENT_CONFIG, zenoh_config

    conf = zenoh_config(DEFAULT_CLIENT_CONFIG, connect=[f"tcp/127.0.0.1:{free_port()}"])
    with pytest.raises(SessionUnavailable):
        open_session(conf, timeout_s=0.6)


def test_node_declares_one_publisher_per_key_and_source(router: Router) -> None:
    with Node(router.client_config(), service="testpeer", instance="pubs", scope="cloud") as node:
        first = node.publisher("route_plan", vehicle="car01")
        assert node.publisher("route_plan", vehicle="car01") is first  # its sequence numbers go on
        assert node.publisher("route_plan", vehicle="car02") is not first
        assert node.publisher("route_plan", vehicle="car01", source_id="cloud/other/x") is not first


def test_a_node_can_declare_its_presence_once_it_is_ready(router: Router) -> None:
    """`present_at_open=False`: the health queryable at once, the presence token only at
    `declare_presence()` (once, however often asked); a node that does not announce itself has none."""
    with Node(router.client_config(), service="test", instance="watcher", scope="site") as watcher:
        key = get_stream("alive").key(scope="site", service="test", instance="late")

        def present() -> bool:
            return bool(alive_tokens(watcher.session, key, timeout_s=0.5))

        with Node(
            router.client_config(), service="test", instance="late", scope="site", present_at_open=False
        ) as late:
            time.sleep(0.3)
            assert not present()
            assert any(r.ok is not None for r in watcher.session.get(late.health_key, timeout=2.0))
            late.declare_presence()
            late.declare_presence()
            wait_until(present, 5.0, "the token once declared")
        wait_until(lambda: not present(), 5.0, "the token gone with the node")
        quiet = Node(router.client_config(), service="test", instance="quiet", scope="site", announce=False)
        with quiet, pytest.raises(RuntimeError, match="does not announce"):
            quiet.declare_presence()

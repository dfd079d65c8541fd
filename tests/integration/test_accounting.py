"""Exact accounting under a slow consumer (issue 17.4): every message that reaches a subscription is
either taken by the consumer or counted as dropped by its queue.

A publisher sends 2000 acks (must-deliver QoS: reliable, BLOCK, so the transport loses none) as fast as
it can; the consumer takes one every 2 ms from an 8-deep drop-oldest queue. Then, from the node's own
counters: decoded (`accepted`) == sent, and taken + `dropped/queue_full` == accepted.
"""

from __future__ import annotations

import threading
import time

import pytest
from rmmdet.v1.planning_pb2 import RouteAck

from shared.bus.node import Node
from tests.helpers import Router

pytestmark = [pytest.mark.integration, pytest.mark.timeout(60)]

SENT = 2000
QUEUE = 8
CONSUME_EVERY_S = 0.002


def test_slow_consumer_sent_equals_taken_plus_counted_drops(router: Router) -> None:
    with (
        Node(router.client_config(), service="test", instance="consumer", scope="site") as consumer,
        Node(router.client_config(), service="test", instance="producer", scope="site") as producer,
    ):
        sub = consumer.subscribe_stream("route_ack", vehicle="v1", maxsize=QUEUE)
        pub = producer.publisher("route_ack", vehicle="v1")
        assert pub.wait_for_subscribers(10.0)
        taken = 0
        done = threading.Event()

        def consume() -> None:
            nonlocal taken
            while not done.is_set() or len(sub.queue):
                if sub.recv(timeout=0.05) is not None:
                    taken += 1
                    time.sleep(CONSUME_EVERY_S)

        thread = threading.Thread(target=consume)
        thread.start()
        for i in range(SENT):
            pub.put(
                RouteAck(vehicle_id="v1", plan_id=f"p{i}", version=i + 1, status=1), stamp_ns=time.time_ns()
            )
        deadline = time.monotonic() + 20
        while consumer.counters.get("accepted") < SENT and time.monotonic() < deadline:
            time.sleep(0.05)
        done.set()
        thread.join(10)
        counters = consumer.counters.snapshot()
    dropped = counters.get("dropped/queue_full", 0)
    print(f"sent {SENT}, decoded {counters.get('accepted')}, taken {taken}, counted dropped {dropped}")
    assert counters.get("accepted") == SENT
    assert taken + dropped == SENT
    assert dropped > 0  # the consumer was slow enough for the queue to overflow

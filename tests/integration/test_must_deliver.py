"""Must-deliver streams on Zenoh's advanced publisher/subscriber (streams.yaml `must_deliver`), through a
real router: a late joiner gets the cached calibration at once (`history: true`); a plan put while the
router was down (the publisher cut off) reaches the subscriber once the router is back, recovered from
the publisher's cache by the subscriber's periodic query, exactly once, and nothing is counted missed."""

from __future__ import annotations

import signal
import time

import pytest
from rmmdet.v1.planning_pb2 import RoutePlan

from shared.bus.node import Node
from shared.paths import DEFAULT_SCENE
from shared.scene.calibration import calibration_set
from shared.scene.scene import Scene
from tests.helpers import start_router, stop

pytestmark = [pytest.mark.integration, pytest.mark.timeout(90)]

WAIT_S = 10.0


def recv_all(sub, until_s: float) -> list:
    out = []
    while time.monotonic() < until_s:
        item = sub.recv(timeout=0.05)
        if item is not None:
            out.append(item)
    return out


def wait_for(sub, pred, timeout_s: float = WAIT_S):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        item = sub.recv(timeout=0.05)
        if item is not None and pred(item):
            return item
    raise AssertionError(f"nothing matching within {timeout_s} s")


def test_a_late_joiner_gets_the_cached_calibration_at_once(router) -> None:
    with Node(router.client_config(), service="sim", instance="calib", scope="sim") as pub_node:
        pub = pub_node.publisher("calibration", agent="agent1")
        calibration = calibration_set(Scene.load(DEFAULT_SCENE), "agent1")
        pub.put(calibration)
        time.sleep(0.5)  # published long before anyone listens
        with Node(router.client_config(), service="mec", instance="agent1", scope="agent1") as sub_node:
            t0 = time.monotonic()
            sub = sub_node.subscribe_stream("calibration", agent="agent1")
            item = wait_for(sub, lambda _item: True, timeout_s=5.0)
            assert item.message.SerializeToString() == calibration.SerializeToString()
            print(f"calibration from the cache {time.monotonic() - t0:.3f} s after subscribing")


def test_a_plan_put_while_the_router_is_down_is_recovered_and_counted() -> None:
    router = start_router()
    try:
        with (
            Node(router.client_config(), service="coordinator", instance="cloud", scope="cloud") as coord,
            Node(router.client_config(), service="sim", instance="sim", scope="sim") as vehicles,
        ):
            sub = vehicles.subscribe_stream("route_plan", vehicle="v01")
            pub = coord.publisher("route_plan", vehicle="v01")
            assert pub.wait_for_subscribers(WAIT_S)
            pub.put(RoutePlan(vehicle_id="v01", plan_id="a" * 32, version=1, lane_ids=["l0"]))
            wait_for(sub, lambda item: item.message.version == 1)

            router.proc.send_signal(signal.SIGKILL)
            router.proc.wait(5)
            deadline = time.monotonic() + WAIT_S
            while coord.uplink.connected:  # the publisher knows it is cut off
                assert time.monotonic() < deadline
                time.sleep(0.01)
            pub.put(
                RoutePlan(vehicle_id="v01", plan_id="b" * 32, version=2, lane_ids=["l0"])
            )  # goes nowhere now
            t_put = time.monotonic()
            router = start_router(router.port)
            item = wait_for(sub, lambda item: item.message.version == 2, timeout_s=WAIT_S)
            print(f"plan put while cut off recovered {time.monotonic() - t_put:.2f} s after the put")
            assert item.message.plan_id == "b" * 32
            assert vehicles.counters.get("missed/route_plan") == 0
            late = recv_all(sub, time.monotonic() + 1.0)
            assert [i.message.version for i in late] == [], "recovered once, not again"
    finally:
        stop(router.proc)

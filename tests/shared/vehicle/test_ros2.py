"""A ROS 2 vehicle's plan as nav_msgs/Path and its PlanAck, CDR through the rosbags typestore
(shared/vehicle/ros2.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rmmdet.v1.planning_pb2 import RoutePlan

from shared.paths import DEFAULT_SCENE
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.traffic.plans import Ack
from shared.vehicle import ros2

STORE = ros2.typestore()


@pytest.fixture(scope="module")
def network() -> RoadNetwork:
    return RoadNetwork(Scene.load(DEFAULT_SCENE))


@pytest.mark.parametrize(
    ("namespace", "topic", "key"),
    [
        ("/v03", "/rmmdet/plan", "v03/rmmdet/plan"),
        ("/", "rmmdet/plan", "rmmdet/plan"),
        ("a/b/", "/t", "a/b/t"),
    ],
)
def test_bridge_keys(namespace: str, topic: str, key: str) -> None:
    """zenoh-bridge-ros2dds: the namespace prefixes every routed interface, leading slash dropped."""
    assert ros2.bridge_key(namespace, topic) == key


def test_a_plan_as_a_path_round_trips_through_cdr(network: RoadNetwork) -> None:
    lanes = ["l0", "l1"]
    plan = RoutePlan(vehicle_id="v03", plan_id="a" * 32, version=1_790_000_000_123_456, lane_ids=lanes)
    path = STORE.deserialize_cdr(ros2.plan_path_cdr(plan, network, STORE), ros2.PATH_TYPE)
    assert (path.header.stamp.sec, path.header.stamp.nanosec) == (1_790_000_000, 123_456_000)
    assert path.header.frame_id == "world"
    expected = ros2.plan_poses(plan, network)
    got = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in path.poses])
    assert np.allclose(got, expected[:, :3])
    first, second = network.lanes["l0"], network.lanes["l1"]
    joined = np.allclose(first.points[-1], second.points[0])
    assert len(path.poses) == len(first.points) + len(second.points) - int(joined)  # no repeated joint
    q = path.poses[0].pose.orientation
    assert math.isclose(2 * math.atan2(q.z, q.w), first.heading[0], abs_tol=1e-9)  # facing along the lane


def test_an_unknown_lane_is_named(network: RoadNetwork) -> None:
    plan = RoutePlan(plan_id="b" * 32, version=1, lane_ids=["l0", "nowhere"])
    with pytest.raises(ValueError, match="lane 'nowhere'"):
        ros2.plan_poses(plan, network)


def test_plan_ack_round_trip_and_refusals() -> None:
    cdr = ros2.plan_ack_cdr(1_790_000_000_123_456_000, Ack.REJECTED_INVALID, "no such lane here", STORE)
    answer = ros2.parse_plan_ack(cdr, STORE)
    assert answer == ros2.CarAnswer(1_790_000_000_123_456_000, Ack.REJECTED_INVALID, "no such lane here")
    with pytest.raises(ValueError, match="not a CDR"):
        ros2.parse_plan_ack(cdr[:9], STORE)  # truncated
    with pytest.raises(ValueError, match="B >"):
        ros2.parse_plan_ack(b"\x00" * (ros2.MAX_PLAN_ACK_BYTES + 1), STORE)
    bad = bytearray(cdr)
    bad[12] = 9  # status (after the 4-byte CDR header and the 8-byte stamp): none of Ack's
    with pytest.raises(ValueError, match="status 9"):
        ros2.parse_plan_ack(bytes(bad), STORE)


def test_the_bridge_configuration_routes_exactly_the_plan_topics() -> None:
    """deploy/ros2's bridge config parses as a Zenoh config and allows the topics this module uses."""
    import json

    import zenoh

    from shared.paths import DEPLOY_DIR

    conf = zenoh.Config.from_file(str(DEPLOY_DIR / "ros2" / "zenoh-bridge-ros2dds.json5"))
    allow = json.loads(conf.get_json("plugins/ros2dds/allow"))
    assert allow["subscribers"] == [f"/{ros2.PLAN_TOPIC}"] and allow["publishers"] == [
        f"/{ros2.PLAN_ACK_TOPIC}"
    ]
    namespace = json.loads(conf.get_json("plugins/ros2dds/namespace"))
    assert ros2.bridge_key(namespace, ros2.PLAN_TOPIC) == "v03/rmmdet/plan"

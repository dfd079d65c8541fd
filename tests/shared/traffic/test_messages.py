"""Conversions to and from rmmdet.v1: agent_objects, traffic_map, route_plan."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rmmdet.v1.geometry_pb2 import Box3D, Vector3
from rmmdet.v1.perception_pb2 import TrackedObject, TrackedObjects
from rmmdet.v1.planning_pb2 import RoutePlan, RoutePolicy
from rmmdet.v1.traffic_pb2 import AgentState, TrafficMap

from shared.scene.road_network import RoadNetwork
from shared.traffic.config import POLICIES, DeliveryConfig, MapConfig
from shared.traffic.coverage import AgentState as State
from shared.traffic.maps import TrafficMapBuilder, Vehicles
from shared.traffic.messages import POLICY_ENUM, agent_objects, route_plan, traffic_map
from shared.traffic.planner import Route
from shared.traffic.plans import PlanBook
from tests.shared.traffic.scenes import map_scene


def tracked(center, size, velocity=(0.0, 0.0, 0.0), existence=1.0, covariance=()) -> TrackedObject:
    return TrackedObject(
        existence_probability=existence,
        box=Box3D(
            center_m=Vector3(x=center[0], y=center[1], z=center[2]),
            size_m=Vector3(x=size[0], y=size[1], z=size[2]),
        ),
        velocity_mps=Vector3(x=velocity[0], y=velocity[1], z=velocity[2]),
        position_covariance_m2=list(covariance),
    )


OBJECTS = TrackedObjects(
    agent_id="agent1",
    objects=[
        tracked(
            (1.0, 2.0, 0.105),
            (0.33, 0.22, 0.21),
            velocity=(0.3, -0.1, 0.0),
            existence=0.9,
            covariance=(0.01, 0.005, 0.004, 0.005, 0.02, 0.003, 0.004, 0.003, 0.03),  # diagonal mean 0.02
        ),
        tracked((0.0, -1.0, 0.5), (0.33, 0.22, 0.2), existence=0.4),  # no covariance: variance 1
        tracked((3.0, 3.0, 0.1), (0.3, 0.2, 0.2), existence=0.1, covariance=(0.5, 0.5)),  # malformed
    ],
)


def test_agent_objects_road_contact_point_and_variance() -> None:
    obj = agent_objects("agent1", OBJECTS)
    assert obj.agent_id == "agent1"
    assert len(obj) == 3
    # road contact: centre z - height / 2
    np.testing.assert_allclose(
        obj.position_m, [(1.0, 2.0, 0.0), (0.0, -1.0, 0.4), (3.0, 3.0, 0.0)], atol=1e-12
    )
    np.testing.assert_allclose(obj.velocity_mps, [(0.3, -0.1, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)])
    np.testing.assert_allclose(obj.position_var_m2, [0.02, 1.0, 1.0])


@pytest.mark.parametrize(("min_existence", "kept"), [(0.0, 3), (0.1, 3), (0.2, 2), (0.5, 1), (0.95, 0)])
def test_agent_objects_existence_filter(min_existence: float, kept: int) -> None:
    obj = agent_objects("agent1", OBJECTS, min_existence)
    assert len(obj) == kept
    assert obj.position_m.shape == (kept, 3)
    assert obj.velocity_mps.shape == (kept, 3)
    assert obj.position_var_m2.shape == (kept,)
    if kept:
        np.testing.assert_allclose(obj.position_m[0], (1.0, 2.0, 0.0), atol=1e-12)


def test_agent_objects_of_an_empty_list() -> None:
    obj = agent_objects("agent2", TrackedObjects(agent_id="agent2"))
    assert (obj.agent_id, len(obj), obj.position_m.shape) == ("agent2", 0, (0, 3))


def snapshot():
    scene = map_scene()
    builder = TrafficMapBuilder(
        scene, RoadNetwork(scene), MapConfig(smoothing_time_constant_s=5.0, grid_cell_m=0.5)
    )
    pos = np.array([(1.0, 0.5, 0.0), (2.0, 0.5, 0.0), (3.0, 1.0, 0.0)])  # two on lo, one off-lane (south)
    vel = np.array([(0.2, 0.0, 0.0), (0.4, 0.0, 0.0), (0.0, 0.0, 0.0)])
    return builder.update(Vehicles(pos, vel, np.full(3, 0.01), [("a",)] * 3), 0.0, {"agent_s"})


def test_traffic_map_fields() -> None:
    snap = snapshot()
    coverage = [
        ("agent_s", State.LIVE, 0.1, 3),
        ("agent_n", State.STALE, 1.5, 0),
        ("agent_x", State.LOST, math.inf, 0),
    ]
    msg = TrafficMap.FromString(traffic_map(snap, coverage, 5.0).SerializeToString())
    assert msg.smoothing_time_constant_s == 5.0

    assert [lane.lane_id for lane in msg.lanes] == ["hi", "lo"]
    hi, lo = msg.lanes
    assert (hi.vehicle_count, hi.speed_valid, hi.mean_speed_mps, hi.observed) == (0, False, 0.0, False)
    assert (lo.vehicle_count, lo.speed_valid, lo.observed) == (2, True, True)
    assert lo.mean_speed_mps == pytest.approx(0.3)
    assert lo.length_m == pytest.approx(3.0)
    assert lo.density_veh_per_m == pytest.approx(2.0 / 3.0)

    assert [a.area_id for a in msg.areas] == ["south", "north"]
    south, north = msg.areas
    assert (south.vehicle_count, south.crowding_rank, south.speed_valid) == (3, 1, True)
    assert south.mean_speed_mps == pytest.approx(0.2)
    assert (north.vehicle_count, north.crowding_rank, north.speed_valid, north.mean_speed_mps) == (
        0,
        0,
        False,
        0.0,
    )

    grid = msg.grid
    assert (grid.origin_m.x_m, grid.origin_m.y_m, grid.cell_size_m) == (-1.0, -1.0, 0.5)
    assert (grid.row_count, grid.column_count) == (6, 10)
    assert len(grid.vehicle_count) == len(grid.mean_speed_mps) == len(grid.speed_samples) == 60
    cells = {i for i, c in enumerate(grid.vehicle_count) if c}
    assert cells == {3 * 10 + 4, 3 * 10 + 6, 4 * 10 + 8}  # row-major: row * columns + column
    assert grid.mean_speed_mps[3 * 10 + 6] == pytest.approx(0.4)
    assert grid.speed_samples[4 * 10 + 8] == 1

    assert [(c.agent_id, c.state, c.object_count) for c in msg.coverage] == [
        ("agent_s", AgentState.AGENT_STATE_LIVE, 3),
        ("agent_n", AgentState.AGENT_STATE_STALE, 0),
        ("agent_x", AgentState.AGENT_STATE_LOST, 0),
    ]
    assert [c.data_age_s for c in msg.coverage] == [pytest.approx(0.1), pytest.approx(1.5), 1e9]  # inf capped


def test_every_policy_has_a_wire_value() -> None:
    assert set(POLICY_ENUM) == set(POLICIES)
    assert len(set(POLICY_ENUM.values())) == len(POLICIES)
    assert RoutePolicy.ROUTE_POLICY_UNSPECIFIED not in POLICY_ENUM.values()


@pytest.mark.parametrize("policy", POLICIES)
def test_route_plan_fields(policy: str) -> None:
    route = Route(["in", "ac", "cb"], ["ja", "jc"], 8.0, 5.0, policy)  # type: ignore[arg-type]
    book = PlanBook(DeliveryConfig(), max_vehicles=16)
    book.issue("car7", route, 0.0, pushed=False, wall_ns=7_000)
    plan = book.latest("car7")
    assert plan is not None
    valid_until_ns = 1_500_000_000_123
    msg = RoutePlan.FromString(
        route_plan(plan, "jb", valid_until_ns, ["agent1"], ["agent2", "agent3"]).SerializeToString()
    )
    assert (msg.vehicle_id, msg.plan_id, msg.version) == ("car7", plan.plan_id, 7)
    assert msg.policy == POLICY_ENUM[policy]
    assert list(msg.lane_ids) == ["in", "ac", "cb"]
    assert list(msg.junction_ids) == ["ja", "jc"]
    assert msg.destination_junction_id == "jb"
    assert (msg.expected_travel_time_s, msg.length_m) == (8.0, 5.0)
    assert msg.valid_until.ToNanoseconds() == valid_until_ns
    assert (msg.valid_until.seconds, msg.valid_until.nanos) == (1500, 123)
    assert list(msg.coverage.live_agents) == ["agent1"]
    assert list(msg.coverage.missing_agents) == ["agent2", "agent3"]


def test_region_maps_merge_into_one_map_for_viewers() -> None:
    from rmmdet.v1.traffic_pb2 import AgentCoverage, AreaTraffic, LaneTraffic, TrafficMap

    from shared.traffic.messages import merge_region_maps

    def region_map(
        observed: dict[str, int], agent: str, cells: list[float], samples: list[int]
    ) -> TrafficMap:
        m = TrafficMap(smoothing_time_constant_s=5.0)
        for lane in ("l0", "l1", "l2"):
            m.lanes.append(
                LaneTraffic(lane_id=lane, vehicle_count=observed.get(lane, 0), observed=lane in observed)
            )
        m.areas.append(AreaTraffic(area_id="ring", vehicle_count=sum(observed.values())))
        m.coverage.append(AgentCoverage(agent_id=agent, state=1))
        g = m.grid
        g.cell_size_m, g.row_count, g.column_count = 0.25, 1, 3
        g.vehicle_count.extend(cells)
        g.speed_samples.extend(samples)
        g.mean_speed_mps.extend([0.1 * s for s in samples])
        return m

    a = region_map({"l0": 2}, "agent2", [1.0, 0.0, 0.5], [3, 0, 1])
    b = region_map({"l1": 1, "l0": 3}, "agent1", [0.0, 2.0, 0.5], [0, 4, 2])
    merged = merge_region_maps([a, b])
    assert [c.agent_id for c in merged.coverage] == ["agent2", "agent1"]
    lanes = {lane.lane_id: (lane.observed, lane.vehicle_count) for lane in merged.lanes}
    assert lanes == {"l0": (True, 3), "l1": (True, 1), "l2": (False, 0)}
    assert list(merged.grid.vehicle_count) == [1.0, 2.0, 0.5]
    assert list(merged.grid.speed_samples) == [3, 4, 2]
    assert list(merged.grid.mean_speed_mps) == pytest.approx([0.3, 0.4, 0.2])  # the map with more samples
    assert merged.areas[0].vehicle_count == 4
    assert merge_region_maps([a]) == a and merge_region_maps([]) == TrafficMap()


def test_latest_region_maps_drop_a_silent_region() -> None:
    from rmmdet.v1.traffic_pb2 import AgentCoverage, TrafficMap

    from shared.traffic.messages import LatestRegionMaps

    maps = LatestRegionMaps(max_age_s=5.0)
    assert maps.merged(0.0) is None
    for region, agent in ((0, "agent2"), (1, "agent1")):
        m = TrafficMap(coverage=[AgentCoverage(agent_id=agent, state=1)])
        maps.put(f"rmmdet/v1/cloud/regions/{region}/traffic", m, 100 + region, now_s=float(region))
    merged = maps.merged(2.0)
    assert merged is not None and [c.agent_id for c in merged[0].coverage] == ["agent2", "agent1"]
    assert merged[1] == 101
    later = maps.merged(5.5)  # region 0 silent for 5.5 s: its shard is gone
    assert later is not None and [c.agent_id for c in later[0].coverage] == ["agent1"]

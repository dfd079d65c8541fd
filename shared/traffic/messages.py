"""Conversions between the bus messages (rmmdet.v1) and the traffic functions' plain types."""

from __future__ import annotations

import numpy as np
from google.protobuf.message import Message
from google.protobuf.timestamp_pb2 import Timestamp
from rmmdet.v1.common_pb2 import Header
from rmmdet.v1.perception_pb2 import TrackedObjects
from rmmdet.v1.planning_pb2 import PlanCoverage, RoutePlan, RoutePolicy, RouteResponse
from rmmdet.v1.traffic_pb2 import AgentCoverage, AgentState, AreaTraffic, LaneTraffic, TrafficMap

from shared.traffic.coverage import AgentState as State
from shared.traffic.maps import AgentObjects, TrafficSnapshot
from shared.traffic.plans import IssuedPlan

POLICY_ENUM = {
    "random": RoutePolicy.ROUTE_POLICY_RANDOM,
    "paper_rule": RoutePolicy.ROUTE_POLICY_PAPER_RULE,
    "shortest": RoutePolicy.ROUTE_POLICY_SHORTEST_DISTANCE,
    "dynamic_ground_truth": RoutePolicy.ROUTE_POLICY_DYNAMIC_GROUND_TRUTH,
    "balanced": RoutePolicy.ROUTE_POLICY_BALANCED,
}
STATE_ENUM = {
    State.LIVE: AgentState.AGENT_STATE_LIVE,
    State.STALE: AgentState.AGENT_STATE_STALE,
    State.LOST: AgentState.AGENT_STATE_LOST,
}
POSITION_AXES = 3


def agent_objects(agent_id: str, msg: TrackedObjects, min_existence: float = 0.0) -> AgentObjects:
    """World-frame positions, velocities and mean position variances of an agent's tracked objects."""
    kept = [o for o in msg.objects if o.existence_probability >= min_existence]
    if not kept:
        return AgentObjects.empty(agent_id)
    # The road-contact point (box bottom centre): lanes and areas are defined on the road surface.
    pos = np.array(
        [[o.box.center_m.x, o.box.center_m.y, o.box.center_m.z - o.box.size_m.z / 2] for o in kept], float
    )
    vel = np.array([[o.velocity_mps.x, o.velocity_mps.y, o.velocity_mps.z] for o in kept], float)
    var = np.array(
        [
            np.mean(np.asarray(o.position_covariance_m2, float)[:: POSITION_AXES + 1][:POSITION_AXES])
            if len(o.position_covariance_m2) == POSITION_AXES * POSITION_AXES
            else 1.0
            for o in kept
        ]
    )
    return AgentObjects(agent_id, pos, vel, var)


def traffic_map(
    snap: TrafficSnapshot,
    coverage: list[tuple[str, State, float, int]],
    smoothing_time_constant_s: float,
) -> TrafficMap:
    """The maps as a TrafficMap (header left to the publisher); coverage = (agent, state, age, count)."""
    msg = TrafficMap(smoothing_time_constant_s=smoothing_time_constant_s)
    for i, lane in enumerate(snap.lane_ids):
        msg.lanes.append(
            LaneTraffic(
                lane_id=lane,
                vehicle_count=int(snap.lane_count[i]),
                density_veh_per_m=float(snap.lane_count_smoothed[i] / snap.lane_length_m[i]),
                mean_speed_mps=float(snap.lane_speed_mps[i]) if snap.lane_speed_valid[i] else 0.0,
                speed_valid=bool(snap.lane_speed_valid[i]),
                length_m=float(snap.lane_length_m[i]),
                observed=bool(snap.lane_observed[i]),
            )
        )
    for i, area in enumerate(snap.area_ids):
        msg.areas.append(
            AreaTraffic(
                area_id=area,
                vehicle_count=int(snap.area_count[i]),
                mean_speed_mps=float(snap.area_speed_mps[i]) if snap.area_speed_valid[i] else 0.0,
                speed_valid=bool(snap.area_speed_valid[i]),
                crowding_rank=int(snap.area_rank[i]),
            )
        )
    grid = msg.grid
    grid.origin_m.x_m, grid.origin_m.y_m = snap.grid_origin_m
    grid.cell_size_m = snap.grid_cell_m
    grid.row_count, grid.column_count = snap.grid_shape
    grid.vehicle_count.extend(snap.grid_count.ravel().tolist())
    grid.mean_speed_mps.extend(snap.grid_speed_mps.ravel().tolist())
    grid.speed_samples.extend(snap.grid_samples.ravel().tolist())
    for agent, state, age_s, count in coverage:
        msg.coverage.append(
            AgentCoverage(
                agent_id=agent,
                state=STATE_ENUM[state],
                data_age_s=min(age_s, 1e9),  # not ns: a cap in seconds
                object_count=count,
            )
        )
    return msg


def route_plan(
    plan: IssuedPlan, destination: str, valid_until_ns: int, live: list[str], missing: list[str]
) -> RoutePlan:
    """An issued plan as a RoutePlan (header left to the publisher)."""
    msg = RoutePlan(
        vehicle_id=plan.vehicle_id,
        plan_id=plan.plan_id,
        version=plan.version,
        policy=POLICY_ENUM[plan.route.policy],
        lane_ids=plan.route.lanes,
        junction_ids=plan.route.junctions,
        destination_junction_id=destination,
        expected_travel_time_s=plan.route.expected_travel_time_s,
        length_m=plan.route.length_m,
        coverage=PlanCoverage(live_agents=live, missing_agents=missing),
    )
    stamp = Timestamp()
    stamp.FromNanoseconds(valid_until_ns)
    msg.valid_until.CopyFrom(stamp)
    return msg


def embed_plan_header(response: Message, header: Header) -> None:
    """The plan inside a RouteResponse carries the reply's header too (pushed plans carry their own)."""
    assert isinstance(response, RouteResponse)
    response.plan.header.CopyFrom(header)

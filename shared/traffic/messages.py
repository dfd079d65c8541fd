"""Conversions between the bus messages (rmmdet.v1) and the traffic functions' plain types."""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
from google.protobuf.message import Message
from google.protobuf.timestamp_pb2 import Timestamp
from numpy.typing import NDArray
from rmmdet.v1.common_pb2 import Header
from rmmdet.v1.perception_pb2 import TrackedObjects
from rmmdet.v1.planning_pb2 import (
    AckStatus,
    PlanCoverage,
    PlanHandover,
    RoutePlan,
    RoutePolicy,
    RouteResponse,
)
from rmmdet.v1.traffic_pb2 import (
    AgentCoverage,
    AgentState,
    AreaTraffic,
    CliquePath,
    LaneTraffic,
    RegionClique,
    TrafficGrid,
    TrafficMap,
)

from shared.traffic.config import PolicyName
from shared.traffic.coverage import AgentState as State
from shared.traffic.maps import AgentObjects, TrafficSnapshot
from shared.traffic.planner import Route
from shared.traffic.plans import PLAN_ID, Ack, ActivePlan, Handover, IssuedPlan
from shared.traffic.regions import Clique

POLICY_ENUM: dict[PolicyName, RoutePolicy.ValueType] = {
    "random": RoutePolicy.ROUTE_POLICY_RANDOM,
    "paper_rule": RoutePolicy.ROUTE_POLICY_PAPER_RULE,
    "shortest": RoutePolicy.ROUTE_POLICY_SHORTEST_DISTANCE,
    "dynamic_ground_truth": RoutePolicy.ROUTE_POLICY_DYNAMIC_GROUND_TRUTH,
    "balanced": RoutePolicy.ROUTE_POLICY_BALANCED,
}
POLICY_NAME: dict[int, PolicyName] = {v: k for k, v in POLICY_ENUM.items()}
STATE_ENUM = {
    State.LIVE: AgentState.AGENT_STATE_LIVE,
    State.STALE: AgentState.AGENT_STATE_STALE,
    State.LOST: AgentState.AGENT_STATE_LOST,
}
POSITION_AXES = 3
#: A clique time on the bus where the region has no way (in memory +inf; the codec refuses non-finite floats).
NO_WAY = -1.0


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


# --- shards (shared/traffic/regions.py, core.py `release` / `adopt`) ---------------------------------


def handover_message(handover: Handover, now_s: float) -> PlanHandover:
    """A released vehicle for the shard that takes it over (header left to the replier)."""
    plan, active = handover.plan, handover.active
    return PlanHandover(
        held=True,
        plan=active.message,
        version_counter=handover.version,
        pushed=plan.pushed,
        sends=plan.sends,
        ack=plan.ack.value if plan.ack is not None else AckStatus.ACK_STATUS_UNSPECIFIED,
        age_s=max(0.0, now_s - plan.issued_s),
        maps_stamp_ns=active.stamp_ns,
    )


def handover_of(msg: PlanHandover, vehicle_id: str, now_s: float) -> Handover:
    """`msg` (a held vehicle, already range-checked by the codec) as the core's Handover, issued `age_s`
    before `now_s` on this shard's clock. ValueError names what does not fit: another vehicle, an id or
    version a coordinator never issues, a route whose junctions do not match its lanes. Whether its
    lanes join is the adopting core's check (it has the network)."""
    plan = msg.plan
    if not msg.held:
        raise ValueError("not held")
    if plan.vehicle_id != vehicle_id:
        raise ValueError(f"handover for {plan.vehicle_id!r}, asked for {vehicle_id!r}")
    if not PLAN_ID.fullmatch(plan.plan_id):
        raise ValueError(f"plan id {plan.plan_id[:40]!r}")
    if not 0 < plan.version <= msg.version_counter:
        raise ValueError(f"version {plan.version} outside (0, {msg.version_counter}]")
    if plan.policy not in POLICY_NAME:
        raise ValueError(f"policy {plan.policy}")
    if not plan.lane_ids or len(plan.junction_ids) != len(plan.lane_ids) - 1:
        raise ValueError(f"{len(plan.lane_ids)} lanes with {len(plan.junction_ids)} junctions")
    if not (math.isfinite(msg.age_s) and msg.age_s >= 0):
        raise ValueError(f"age {msg.age_s}")
    ack = None if msg.ack == AckStatus.ACK_STATUS_UNSPECIFIED else Ack(msg.ack)
    route = Route(
        list(plan.lane_ids),
        list(plan.junction_ids),
        plan.expected_travel_time_s,
        plan.length_m,
        POLICY_NAME[plan.policy],
    )
    issued = IssuedPlan(
        vehicle_id,
        plan.plan_id,
        plan.version,
        route,
        now_s - msg.age_s,
        msg.pushed,
        sends=msg.sends,
        last_send_s=now_s if msg.sends else 0.0,  # a pending resend waits a full ack timeout here
        ack=ack,
    )
    message = RoutePlan()
    message.CopyFrom(plan)
    message.ClearField("header")
    message.ClearField("signature")
    message.ClearField("key_id")
    active = ActivePlan(
        plan.destination_junction_id,
        frozenset(plan.coverage.missing_agents),
        message,
        msg.maps_stamp_ns,
        plan.valid_until.ToNanoseconds(),
    )
    return Handover(issued, msg.version_counter, active)


def clique_message(clique: Clique) -> RegionClique:
    """A shard's clique for the bus (header left to the publisher): +inf (no way) as NO_WAY."""
    msg = RegionClique(
        region=clique.region,
        entering_lane_ids=clique.entering,
        leaving_lane_ids=clique.leaving,
        time_s=_on_wire(clique.time_s),
        junction_ids=clique.junctions,
        to_junction_s=_on_wire(clique.to_junction_s),
    )
    for (a, b), lanes in clique.paths.items():
        msg.paths.append(CliquePath(from_lane=a, to_lane=b, lane_ids=lanes))
    for (a, junction), lanes in clique.junction_paths.items():
        msg.paths.append(CliquePath(from_lane=a, to_junction=junction, lane_ids=lanes))
    return msg


def clique_of(msg: RegionClique) -> Clique:
    """`msg` as a Clique; ValueError when its matrices do not match its lane and junction lists or a
    path is both or neither kind. Whether it fits the region is `Overlay.clique_problem`'s check."""
    rows = len(msg.entering_lane_ids)
    if len(msg.time_s) != rows * len(msg.leaving_lane_ids):
        raise ValueError(f"{len(msg.time_s)} times for {rows} x {len(msg.leaving_lane_ids)} lanes")
    if len(msg.to_junction_s) != rows * len(msg.junction_ids):
        raise ValueError(f"{len(msg.to_junction_s)} times for {rows} x {len(msg.junction_ids)} junctions")
    paths: dict[tuple[str, str], list[str]] = {}
    junction_paths: dict[tuple[str, str], list[str]] = {}
    for p in msg.paths:
        if bool(p.to_lane) == bool(p.to_junction):
            raise ValueError(f"path from {p.from_lane!r} needs one of to_lane and to_junction")
        (paths if p.to_lane else junction_paths)[(p.from_lane, p.to_lane or p.to_junction)] = list(p.lane_ids)
    return Clique(
        msg.region,
        list(msg.entering_lane_ids),
        list(msg.leaving_lane_ids),
        _off_wire(msg.time_s).reshape(rows, len(msg.leaving_lane_ids)),
        paths,
        list(msg.junction_ids),
        _off_wire(msg.to_junction_s).reshape(rows, len(msg.junction_ids)),
        junction_paths,
    )


def _on_wire(times_s: NDArray[np.float64]) -> list[float]:
    return np.where(np.isposinf(times_s), NO_WAY, times_s).ravel().tolist()


def _off_wire(times_s: Iterable[float]) -> NDArray[np.float64]:
    """NO_WAY back to +inf; any other negative time stays, for `Overlay.clique_problem` to refuse."""
    a = np.array(times_s, float)
    return np.where(a == NO_WAY, np.inf, a)


def merge_region_maps(maps: list[TrafficMap]) -> TrafficMap:
    """One map for viewers out of a sharded coordinator's region maps (each counts only what its own
    agents see, over the whole network): every agent's coverage; per lane the entry of a map that
    observes it (the most vehicles where several do); per grid cell and area the largest count, with the
    speed of the map holding the most samples there. Maps with another grid than the first are left
    out of the grid. Header and smoothing from the first map."""
    if not maps:
        return TrafficMap()
    out = TrafficMap()
    out.CopyFrom(maps[0])
    del out.coverage[:]
    for m in maps:
        out.coverage.extend(m.coverage)
    best: dict[str, LaneTraffic] = {}
    for m in maps:
        for lane in m.lanes:
            held = best.get(lane.lane_id)
            if held is None or (lane.observed, lane.vehicle_count) > (held.observed, held.vehicle_count):
                best[lane.lane_id] = lane
    del out.lanes[:]
    out.lanes.extend(best[lane.lane_id] for lane in maps[0].lanes if lane.lane_id in best)
    areas: dict[str, AreaTraffic] = {}
    for m in maps:
        for area in m.areas:
            held_area = areas.get(area.area_id)
            if held_area is None or area.vehicle_count > held_area.vehicle_count:
                areas[area.area_id] = area
    del out.areas[:]
    out.areas.extend(areas[a.area_id] for a in maps[0].areas if a.area_id in areas)
    grids = [m.grid for m in maps if _same_grid(m.grid, maps[0].grid)]
    if len(grids) > 1 and grids[0].vehicle_count:
        counts = np.array([g.vehicle_count for g in grids], float)
        samples = np.array([g.speed_samples for g in grids], float)
        speeds = np.array([g.mean_speed_mps for g in grids], float)
        pick = samples.argmax(axis=0)
        cells = np.arange(counts.shape[1])
        out.grid.vehicle_count[:] = counts.max(axis=0).tolist()
        out.grid.speed_samples[:] = samples.max(axis=0).astype(int).tolist()
        out.grid.mean_speed_mps[:] = speeds[pick, cells].tolist()
    return out


def _same_grid(a: TrafficGrid, b: TrafficGrid) -> bool:
    return (a.origin_m.x_m, a.origin_m.y_m, a.cell_size_m, a.row_count, a.column_count) == (
        b.origin_m.x_m, b.origin_m.y_m, b.cell_size_m, b.row_count, b.column_count)  # fmt: skip


class LatestRegionMaps:
    """The latest map of each region shard (by key) for viewers, merged (`merge_region_maps`); a region
    not heard for `max_age_s` (its shard gone) drops out of the merge. Seconds on the caller's clock."""

    def __init__(self, max_age_s: float = 5.0) -> None:
        self.max_age_s = max_age_s
        self._latest: dict[str, tuple[float, TrafficMap, int]] = {}

    def put(self, key: str, msg: TrafficMap, stamp_ns: int, now_s: float) -> None:
        self._latest[key] = (now_s, msg, stamp_ns)

    def merged(self, now_s: float) -> tuple[TrafficMap, int] | None:
        """The merged map and its newest stamp (ns), or None when no region is fresh."""
        for key in [k for k, (at_s, _, _) in self._latest.items() if now_s - at_s > self.max_age_s]:
            del self._latest[key]
        if not self._latest:
            return None
        fresh = [self._latest[k] for k in sorted(self._latest)]
        return merge_region_maps([m for _, m, _ in fresh]), max(s for _, _, s in fresh)

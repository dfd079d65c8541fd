"""Route planning on the lane graph for connected vehicles, with the baselines of the flow experiment.

Policies (`PlannerConfig.policy`):
  random               a uniformly random next lane (the paper's "before")
  paper_rule           next lane minimising (cars on lane + 1) x (crowding rank of its area + 1), first on
                       ties (rmmdet_reference.md §D.3); one junction at a time, no destination
  shortest             shortest distance to the destination (static)
  dynamic_ground_truth shortest time on measured lane speeds (SUMO-style rerouting; fed with ground truth)
  balanced             shortest expected time on the perceived maps: lane time at the perceived speed, a
                       queue delay per car on the lane, and a load term per vehicle already planned onto
                       it, so successive plans spread over alternatives instead of all taking one road

A route is a list of lanes starting with the vehicle's current lane; consecutive lanes meet at a
junction. Units: metres, seconds, m/s.
"""

from __future__ import annotations

import itertools
import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import networkx as nx
import numpy as np

from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.traffic.config import PlannerConfig, PolicyName
from shared.traffic.maps import TrafficSnapshot

ONE_JUNCTION_POLICIES = ("random", "paper_rule")


@dataclass
class LaneConditions:
    """What a planner knows about the lanes now. Missing entries: nothing known."""

    count: dict[str, float] = field(default_factory=dict)  # vehicles on the lane
    speed_mps: dict[str, float] = field(default_factory=dict)  # valid measured mean speed
    area_rank: dict[str, int] = field(default_factory=dict)  # area id -> crowding rank (0 = emptiest)

    @classmethod
    def from_snapshot(cls, snap: TrafficSnapshot) -> LaneConditions:
        """Counts of observed lanes and valid speeds; unobserved lanes stay unknown."""
        count = {
            lane: float(snap.lane_count[i]) for i, lane in enumerate(snap.lane_ids) if snap.lane_observed[i]
        }
        speed = {
            lane: float(snap.lane_speed_mps[i])
            for i, lane in enumerate(snap.lane_ids)
            if snap.lane_speed_valid[i]
        }
        rank = {area: int(snap.area_rank[i]) for i, area in enumerate(snap.area_ids)}
        return cls(count, speed, rank)


@dataclass(frozen=True)
class Route:
    lanes: list[str]  # current lane first
    junctions: list[str]  # junction between each pair of consecutive lanes
    expected_travel_time_s: float  # from the end of the current lane to the end of the last
    length_m: float
    policy: PolicyName


class NoRouteError(ValueError):
    """Unknown lane or junction, or the destination cannot be reached."""


class RoutePlanner:
    """Plans routes for vehicles; remembers what it planned so later plans account for that load."""

    def __init__(self, scene: Scene, network: RoadNetwork, cfg: PlannerConfig) -> None:
        self.scene = scene
        self.net = network
        self.cfg = cfg
        self.rng = np.random.default_rng(cfg.seed)
        self.free_speed_mps = {lane.id: lane.speed_limit_mps for lane in scene.spec.lanes}
        self.lane_area = {lane.id: lane.area for lane in scene.spec.lanes}
        self.junctions = {j.id for j in scene.spec.junctions}
        self._planned: dict[str, list[str]] = {}  # vehicle -> lanes ahead it was planned onto

    # --- load bookkeeping ------------------------------------------------------------------------

    def commit(self, vehicle_id: str, route: Route) -> None:
        """Count `route` (beyond the current lane) as future load for other vehicles' plans."""
        self._planned[vehicle_id] = route.lanes[1 : 1 + self.cfg.load_horizon_lanes]

    def forget(self, vehicle_id: str) -> None:
        self._planned.pop(vehicle_id, None)

    def planned_load(self, exclude: str | None = None) -> Counter[str]:
        load: Counter[str] = Counter()
        for vid, lanes in self._planned.items():
            if vid != exclude:
                load.update(lanes)
        return load

    # --- costs -----------------------------------------------------------------------------------

    def lane_time_s(
        self, lane: str, cond: LaneConditions, policy: PolicyName, load: Counter[str] | None = None
    ) -> float:
        """Expected time to drive `lane` (and wait at its end) under `policy`'s cost model."""
        free = self.free_speed_mps[lane]
        length = self.net.lanes[lane].length_m
        if policy == "shortest":
            return length / free
        speed = min(max(cond.speed_mps.get(lane, free), self.cfg.min_speed_mps), free)
        t = length / speed
        if policy == "balanced":
            queued = cond.count.get(lane, 0.0) + self.cfg.load_weight * (load[lane] if load else 0)
            t += self.cfg.junction_service_s * queued
        return t

    def route_time_s(self, lanes: list[str], cond: LaneConditions, policy: PolicyName, exclude: str) -> float:
        """Expected time of `lanes` after the first (the vehicle is on the first)."""
        load = self.planned_load(exclude)
        total = 0.0
        for a, b in itertools.pairwise(lanes):
            total += self._edge_time_s(a, b, cond, policy, load)
        return total

    def _edge_time_s(
        self, a: str, b: str, cond: LaneConditions, policy: PolicyName, load: Counter[str]
    ) -> float:
        connector_m = self.net.graph.edges[a, b]["weight"] - self.net.lanes[b].length_m
        return connector_m / self.free_speed_mps[b] + self.lane_time_s(b, cond, policy, load)

    # --- planning --------------------------------------------------------------------------------

    def plan(
        self,
        vehicle_id: str,
        current_lane: str,
        destination: str,
        cond: LaneConditions,
        policy: PolicyName | None = None,
    ) -> Route:
        """A route from `current_lane` toward junction `destination` (one lane for the one-junction
        policies). Raises NoRouteError on unknown ids or an unreachable destination."""
        policy = policy or self.cfg.policy
        if current_lane not in self.net.lanes:
            raise NoRouteError(f"unknown lane {current_lane!r}")
        if destination not in self.junctions:
            raise NoRouteError(f"unknown junction {destination!r}")
        options = self.net.successors[current_lane]
        if not options and policy in ONE_JUNCTION_POLICIES:
            raise NoRouteError(f"lane {current_lane} is a dead end")
        if policy == "random":
            lanes = [current_lane, options[int(self.rng.integers(len(options)))]]
        elif policy == "paper_rule":
            lanes = [current_lane, min(options, key=lambda lane: self._paper_score(lane, cond))]
        else:
            lanes = self._fastest(current_lane, destination, cond, policy, vehicle_id)
        junctions = [self.net.lane_end_junction(lane) for lane in lanes[:-1]]
        length = self.net.lanes[current_lane].length_m + self.net.route_length_m(lanes)
        time_s = self.route_time_s(lanes, cond, policy, vehicle_id)
        return Route(lanes, junctions, time_s, length, policy)

    def _paper_score(self, lane: str, cond: LaneConditions) -> float:
        rank = cond.area_rank.get(self.lane_area[lane], 0)
        return (cond.count.get(lane, 0.0) + 1.0) * (rank + 1.0)

    def _fastest(
        self, current_lane: str, destination: str, cond: LaneConditions, policy: PolicyName, vehicle_id: str
    ) -> list[str]:
        if self.net.lane_end_junction(current_lane) == destination:
            return [current_lane]
        load = self.planned_load(vehicle_id)

        def weight(a: str, b: str, _data: dict[str, Any]) -> float:
            return self._edge_time_s(a, b, cond, policy, load)

        times, paths = nx.single_source_dijkstra(self.net.graph, current_lane, weight=weight)
        best, best_t = None, math.inf
        for lane, t in times.items():
            if lane != current_lane and self.net.lane_end_junction(lane) == destination and t < best_t:
                best, best_t = paths[lane], t
        if best is None:
            raise NoRouteError(f"junction {destination} is unreachable from lane {current_lane}")
        return list(best)

"""Route planning on the lane graph for connected vehicles, with the baselines of the flow experiment.

Policies (`PlannerConfig.policy`):
  random               a uniformly random next lane (the paper's "before")
  paper_rule           next lane minimising (cars on lane + 1) x (crowding rank of its area + 1), first on
                       ties (docs/references.md, the paper (D.3)); one junction at a time, no destination
  shortest             shortest distance to the destination (static)
  dynamic_ground_truth shortest time on measured lane speeds (SUMO-style rerouting; fed with ground truth)
  balanced             shortest expected time on the perceived maps: lane time at the perceived speed, a
                       queue delay per car on the lane, and a load term per vehicle already planned onto
                       it, so successive plans spread over alternatives instead of all taking one road

A route is a list of lanes starting with the vehicle's current lane; consecutive lanes meet at a
junction. A shard of a sharded coordinator (`ShardView`) plans the same way over the overlay of regions
(shared/traffic/regions.py): its own lanes at their times, other regions by the cliques they published.
Units: metres, seconds, m/s.
"""

from __future__ import annotations

import itertools
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.traffic.config import PlannerConfig, PolicyName
from shared.traffic.maps import TrafficSnapshot
from shared.traffic.regions import Clique, Overlay, connector_times_s

ONE_JUNCTION_POLICIES = ("random", "paper_rule")
FloatArray = NDArray[np.float64]


@dataclass
class LaneConditions:
    """What a planner knows about the lanes now. Missing entries: nothing known (no car, free speed)."""

    count: dict[str, float] = field(default_factory=dict)  # vehicles on the lane (counted or prior)
    speed_mps: dict[str, float] = field(default_factory=dict)  # valid measured mean speed
    area_rank: dict[str, int] = field(default_factory=dict)  # area id -> crowding rank (0 = emptiest)

    @classmethod
    def from_snapshot(cls, snap: TrafficSnapshot) -> LaneConditions:
        """Counts of observed lanes, the density prior of unobserved ones (no lane counts as empty for
        want of a sensor), valid speeds (unobserved or empty lanes: the speed limit)."""
        count = dict(zip(snap.lane_ids, snap.lane_count_expected.tolist(), strict=True))
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


@dataclass
class ShardView:
    """A coordinator shard's place in a sharded network: the overlay, its region, and the latest clique
    each region published, its own included (a region without one is not crossed; a lost shard's: a
    prior)."""

    overlay: Overlay
    region: int
    cliques: dict[int, Clique] = field(default_factory=dict)

    def owns(self, lane: str) -> bool:
        return bool(self.overlay.lane_region[self.overlay.index[lane]] == self.region)


class RoutePlanner:
    """Plans routes for vehicles; remembers what it planned so later plans account for that load.

    Lane times are computed for every lane at once (numpy) and the fastest route comes from scipy's
    Dijkstra on a sparse lane graph whose edge costs are rewritten in place per plan: a plan costs
    tens of microseconds, so a coordinator can replan a whole fleet at every map update."""

    def __init__(
        self, scene: Scene, network: RoadNetwork, cfg: PlannerConfig, shard: ShardView | None = None
    ) -> None:
        self.scene = scene
        self.net = network
        self.cfg = cfg
        self.shard = shard
        self.rng = np.random.default_rng(cfg.seed)
        self.free_speed_mps = {lane.id: lane.speed_limit_mps for lane in scene.spec.lanes}
        self.lane_area = {lane.id: lane.area for lane in scene.spec.lanes}
        self.junctions = {j.id for j in scene.spec.junctions}
        self._planned: dict[str, list[str]] = {}  # vehicle -> lanes ahead it was planned onto
        # Lane graph as arrays: lane k <-> self.lane_ids[k]; edge e goes src[e] -> dst[e].
        self.lane_ids = sorted(network.lanes)
        self._index = {lane: k for k, lane in enumerate(self.lane_ids)}
        self._length_m = np.array([network.lanes[lane].length_m for lane in self.lane_ids])
        self._free_mps = np.array([self.free_speed_mps[lane] for lane in self.lane_ids])
        edges = list(network.graph.edges)
        src = np.array([self._index[a] for a, _ in edges], dtype=np.int64)
        dst = np.array([self._index[b] for _, b in edges], dtype=np.int64)
        connector_s = connector_times_s(network, edges, cfg.turn_penalty_s)
        self._connector_s = dict(zip(edges, connector_s.tolist(), strict=True))
        n = len(self.lane_ids)
        # Build the CSR once; `_order` maps its data slots to our edges so costs can be written in place.
        self._graph = csr_matrix((np.arange(1, len(edges) + 1, dtype=float), (src, dst)), shape=(n, n))
        self._order = self._graph.data.astype(np.int64) - 1
        self._edge_dst = dst[self._order]
        self._edge_connector_s = connector_s[self._order]
        self._free_time_s = self._length_m / self._free_mps
        self._load = np.zeros(n)  # vehicles planned onto each lane (the sum of all `_planned`)
        self._cond: LaneConditions | None = None  # the conditions `_speed` / `_count` were built from
        self._speed = self._free_mps.copy()
        self._count = np.zeros(n)
        self._ends_at: dict[str, NDArray[np.int64]] = {
            j: np.array([self._index[lane] for lane in self.lane_ids if network.lane_end_junction(lane) == j])
            for j in self.junctions
        }

    # --- load bookkeeping ------------------------------------------------------------------------

    def commit(self, vehicle_id: str, route: Route) -> None:
        """Count `route` (beyond the current lane) as future load for other vehicles' plans."""
        self.forget(vehicle_id)
        lanes = route.lanes[1 : 1 + self.cfg.load_horizon_lanes]
        self._planned[vehicle_id] = lanes
        np.add.at(self._load, self._indices(lanes), 1.0)

    def forget(self, vehicle_id: str) -> None:
        old = self._planned.pop(vehicle_id, None)
        if old:
            np.subtract.at(self._load, self._indices(old), 1.0)

    def planned_load(self, exclude: str | None = None) -> Counter[str]:
        load = self._load_array(exclude)
        return Counter({lane: round(float(load[k])) for k, lane in enumerate(self.lane_ids) if load[k] > 0})

    def _indices(self, lanes: list[str]) -> NDArray[np.int64]:
        return np.array([self._index[lane] for lane in lanes], dtype=np.int64)

    def _load_array(self, exclude: str | None) -> FloatArray:
        """(L,) planned vehicles per lane, without `exclude`'s own plan."""
        own = self._planned.get(exclude or "")
        if not own:
            return self._load
        load = self._load.copy()
        np.subtract.at(load, self._indices(own), 1.0)
        return load

    # --- costs -----------------------------------------------------------------------------------

    def lane_time_s(
        self, lane: str, cond: LaneConditions, policy: PolicyName, load: Counter[str] | None = None
    ) -> float:
        """Expected time to drive `lane` (and wait at its end) under `policy`'s cost model."""
        load_arr = np.zeros(len(self.lane_ids))
        for name, c in (load or {}).items():
            load_arr[self._index[name]] = c
        return float(self._lane_times(cond, policy, load_arr)[self._index[lane]])

    def _observe(self, cond: LaneConditions) -> None:
        """Speeds and counts of `cond` as arrays, rebuilt only when the conditions object changes (one
        map update serves many plans)."""
        if cond is self._cond:
            return
        self._speed = self._free_mps.copy()
        self._count = np.zeros(len(self.lane_ids))
        for lane, v in cond.speed_mps.items():
            if lane in self._index:
                self._speed[self._index[lane]] = v
        for lane, c in cond.count.items():
            if lane in self._index:
                self._count[self._index[lane]] = c
        self._speed = np.minimum(np.maximum(self._speed, self.cfg.min_speed_mps), self._free_mps)
        self._cond = cond

    def _lane_times(self, cond: LaneConditions, policy: PolicyName, load: FloatArray) -> FloatArray:
        """(L,) lane times: length at the measured (else free) speed (balanced: per `speed_source`);
        balanced adds a junction service per car on the lane and per vehicle planned onto it (weighted)."""
        if policy == "shortest":
            return self._free_time_s
        self._observe(cond)
        speed = self._free_mps if policy == "balanced" and self.cfg.speed_source == "free" else self._speed
        t = self._length_m / speed
        if policy == "balanced":
            t = t + self.cfg.junction_service_s * (self._count + self.cfg.load_weight * load)
        return t

    def route_time_s(self, lanes: list[str], cond: LaneConditions, policy: PolicyName, exclude: str) -> float:
        """Expected time of `lanes` after the first (the vehicle is on the first)."""
        return self._route_time_s(lanes, self._lane_times(cond, policy, self._load_array(exclude)))

    def _route_time_s(self, lanes: list[str], times: FloatArray) -> float:
        total = 0.0
        for a, b in itertools.pairwise(lanes):
            total += self._connector_s[(a, b)] + float(times[self._index[b]])
        return total

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
        times = self._lane_times(cond, policy, self._load_array(vehicle_id))
        if policy == "random":
            lanes = [current_lane, options[int(self.rng.integers(len(options)))]]
        elif policy == "paper_rule":
            lanes = [current_lane, min(options, key=lambda lane: self._paper_score(lane, cond))]
        else:
            lanes = self._fastest_of(current_lane, destination, times)
            if policy == "balanced" and self.cfg.detour_min_saving > 0:
                lanes = self._unless_it_saves(lanes, current_lane, destination, times)
        return self._route(lanes, times, policy)

    def _fastest_of(
        self, current_lane: str, destination: str, times: FloatArray, free_flow: bool = False
    ) -> list[str]:
        """The fastest route on `times`: on the whole graph, or a shard's overlay (`free_flow`: every
        region's clique at free flow, not as published)."""
        if self.shard is None:
            return self._fastest(current_lane, destination, times)
        shard = self.shard
        if free_flow:
            shard = ShardView(shard.overlay, shard.region, shard.overlay.free_flow_cliques())
        return self._fastest_sharded(shard, current_lane, destination, times)

    def _unless_it_saves(
        self, fastest: list[str], current_lane: str, destination: str, times: FloatArray
    ) -> list[str]:
        """`fastest`, or the free-flow shortest route when `fastest` does not save more than
        `detour_min_saving` of that route's time on `times`."""
        shortest = self._fastest_of(current_lane, destination, self._free_time_s, free_flow=True)
        if shortest == fastest:
            return fastest
        shortest_s = self._route_time_s(shortest, times)
        saves_s = shortest_s - self._route_time_s(fastest, times)
        return fastest if saves_s > self.cfg.detour_min_saving * shortest_s else shortest

    def clique(self, cond: LaneConditions, policy: PolicyName | None = None) -> Clique:
        """This shard's clique on `cond` (what it publishes to the other shards)."""
        if self.shard is None:
            raise ValueError("not a shard: no region to publish")
        times = self._lane_times(cond, policy or self.cfg.policy, self._load)
        return self.shard.overlay.clique(self.shard.region, times)

    def _fastest_sharded(
        self, shard: ShardView, current_lane: str, destination: str, times: FloatArray
    ) -> list[str]:
        """`_fastest` over the overlay: the own region on `times`, the others by their published cliques
        (the own one too, for a route that leaves and comes back: as published at the last map update,
        else computed now)."""
        if self.net.lane_end_junction(current_lane) == destination:
            return [current_lane]
        cliques = shard.cliques
        if shard.region not in cliques:
            cliques = {**cliques, shard.region: shard.overlay.clique(shard.region, times)}
        try:
            return [current_lane, *shard.overlay.route(current_lane, destination, times, cliques)]
        except ValueError as err:
            raise NoRouteError(str(err)) from None

    def route(self, vehicle_id: str, lanes: list[str], cond: LaneConditions, policy: PolicyName) -> Route:
        """`lanes` (the vehicle's current lane first) as a Route, timed like a plan for this vehicle."""
        return self._route(lanes, self._lane_times(cond, policy, self._load_array(vehicle_id)), policy)

    def _route(self, lanes: list[str], times: FloatArray, policy: PolicyName) -> Route:
        junctions = [self.net.lane_end_junction(lane) for lane in lanes[:-1]]
        length = self.net.lanes[lanes[0]].length_m + self.net.route_length_m(lanes)
        return Route(lanes, junctions, self._route_time_s(lanes, times), length, policy)

    def _paper_score(self, lane: str, cond: LaneConditions) -> float:
        rank = cond.area_rank.get(self.lane_area[lane], 0)
        return (cond.count.get(lane, 0.0) + 1.0) * (rank + 1.0)

    def _fastest(self, current_lane: str, destination: str, times: FloatArray) -> list[str]:
        if self.net.lane_end_junction(current_lane) == destination:
            return [current_lane]
        self._graph.data[:] = self._edge_connector_s + times[self._edge_dst]
        source = self._index[current_lane]
        dist, pred = dijkstra(self._graph, indices=source, return_predecessors=True)
        targets = self._ends_at[destination]
        targets = targets[targets != source]
        if len(targets) == 0 or not np.isfinite(dist[targets]).any():
            raise NoRouteError(f"junction {destination} is unreachable from lane {current_lane}")
        k = int(targets[np.argmin(dist[targets])])
        path = [k]
        while k != source:
            k = int(pred[k])
            path.append(k)
        return [self.lane_ids[i] for i in reversed(path)]

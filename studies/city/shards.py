"""The coordinator split into region shards, in lock step (the city study and its tests): one production
`CoordinatorCore` per region (shared/traffic/regions.py), each fed only by its region's roadside agents
and serving only the vehicles on its lanes; after each map update every live shard publishes its clique
and the others plan across its region with it (a lost shard's region by a free-flow prior).

A request goes to the shard owning the vehicle's lane. A shard that does not hold the vehicle asks
the others to release it (`CoordinatorCore.release`) and adopts what comes back (its version counter;
the request is planned afresh): one owner at a time, never two (checked on every handover), no gap.
What the live shards do over Zenoh (a query to the other shards for the vehicle) is the same two calls.
"""

from __future__ import annotations

import logging
import time
from collections import Counter, defaultdict
from typing import Any

import numpy as np
from rmmdet.v1.common_pb2 import ErrorCode
from rmmdet.v1.planning_pb2 import RoutePlan, RouteRequest

from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.traffic.config import CoordinatorSettings
from shared.traffic.core import CoordinatorCore, RequestRejected
from shared.traffic.lanes import lane_agents
from shared.traffic.maps import AgentObjects
from shared.traffic.planner import ShardView
from shared.traffic.plans import Ack
from shared.traffic.regions import Overlay, RegionMap, agent_regions

log = logging.getLogger(__name__)
NOT_FOUND = ErrorCode.ERROR_CODE_NOT_FOUND
UNAVAILABLE = ErrorCode.ERROR_CODE_UNAVAILABLE


class ShardedCoordinator:
    """`regions.regions` cores over `scene`; `kill` / `restart` a shard to test its loss."""

    def __init__(
        self, scene: Scene, settings: CoordinatorSettings, regions: RegionMap, max_vehicles: int
    ) -> None:
        self.scene = scene
        self.settings = settings
        self.net = RoadNetwork(scene)
        self.regions = regions
        self.overlay = Overlay(self.net, regions, settings.planner.turn_penalty_s)
        self.agent_region = agent_regions(lane_agents(scene, self.net), self.net, regions)
        self.max_vehicles = max_vehicles
        self.shards: dict[int, CoordinatorCore | None] = {r: self._start(r) for r in range(regions.regions)}
        self.free_s = self.overlay.free_time_s  # a lost shard's region's prior, and a clique's floor
        self.priors = self.overlay.free_flow_cliques()
        self.counts: Counter[str] = Counter()
        self.busy_s: defaultdict[int, float] = defaultdict(float)  # this step's work per shard, s
        self.step_ms: dict[int, list[float]] = {}  # per shard, its work in each step, ms

    def _start(self, region: int) -> CoordinatorCore:
        if self.regions.regions == 1:  # one shard: the coordinator as it runs unsharded
            return CoordinatorCore(self.scene, self.settings, self.max_vehicles)
        agents = [a for a, r in self.agent_region.items() if r == region]
        view = ShardView(self.overlay, region)
        return CoordinatorCore(self.scene, self.settings, self.max_vehicles, shard=view, shard_agents=agents)

    def live(self) -> dict[int, CoordinatorCore]:
        return {r: core for r, core in self.shards.items() if core is not None}

    def kill(self, region: int) -> None:
        """The shard's process is gone: its state with it; the others plan across its region on a prior."""
        self.shards[region] = None
        self.counts["killed"] += 1

    def restart(self, region: int) -> None:
        self.shards[region] = self._start(region)
        self.counts["restarted"] += 1

    def update(self, objects: list[AgentObjects], now_s: float, now_ns: int) -> list[RoutePlan]:
        """Every live shard takes its agents' objects and ticks; cliques are exchanged; the plans due."""
        live = self.live()
        mine: dict[int, list[AgentObjects]] = {r: [] for r in live}
        for o in objects:
            region = self.agent_region.get(o.agent_id, -1)
            if region in mine:
                mine[region].append(o)
        due: list[RoutePlan] = []
        published = {}
        for r, core in live.items():
            t0 = time.perf_counter()  # one shard's map + re-plan work: what its own process would do
            for o in mine[r]:
                core.on_objects(o.agent_id, o, now_ns, now_s)
            core.tick(now_s, now_ns)
            due += [plan for plan, _stamp_ns, _first in core.due(now_s)]
            if self.regions.regions > 1:
                clique = core.clique()
                problem = self.overlay.clique_problem(clique, self.free_s)
                if problem is None:
                    published[r] = clique
                else:  # as a receiving shard would: refused, counted, its region planned on the prior
                    self.counts[f"rejected/{problem}"] += 1
            self.busy_s[r] += time.perf_counter() - t0
        combined = {**self.priors, **published}  # one object for all: the overlay's searches are shared
        for core in live.values():
            if core.shard is not None:
                core.shard.cliques = combined
        return due

    def end_step(self) -> None:
        """Close a step's timing: each live shard's busy time in it (map updates and plans) is kept."""
        for r, busy in self.busy_s.items():
            if self.shards.get(r) is not None:
                self.step_ms.setdefault(r, []).append(busy * 1e3)
        self.busy_s = defaultdict(float)

    def serve(self, req: RouteRequest, now_s: float, wall_ns: int) -> RoutePlan:
        """The owner shard's plan for `req` (taking the vehicle over first if another shard holds it).
        Raises RequestRejected ("no_shard" when the owner is down)."""
        if req.current_lane_id not in self.net.lanes:
            raise RequestRejected("unknown_lane", NOT_FOUND, f"unknown lane {req.current_lane_id!r}")
        region = self.regions.lane_region(self.net, req.current_lane_id)
        core = self.shards[region]
        if core is None:
            raise RequestRejected("no_shard", UNAVAILABLE, f"region {region}'s shard is down")
        vid = req.vehicle_id
        if not core.owns_vehicle(vid):
            holders = [r for r, other in self.live().items() if r != region and other.owns_vehicle(vid)]
            if len(holders) > 1:
                raise AssertionError(f"{vid} held by shards {holders}")  # never two owners
            if holders:
                other = self.shards[holders[0]]
                assert other is not None
                handover = other.release(vid)
                if handover is not None:
                    core.adopt(handover, now_s, wall_ns)
                    self.counts["handovers"] += 1
        t0 = time.perf_counter()
        plan, _ = core.serve(req, now_s, wall_ns)
        self.busy_s[region] += time.perf_counter() - t0
        self.counts[f"served/{region}"] += 1
        for event in ("killed", "restarted"):
            if self.counts[event]:
                self.counts[f"served_since_{event}/{region}"] += 1
        return plan

    def on_ack(self, vehicle_id: str, plan_id: str, version: int, status: Ack, now_s: float) -> None:
        for core in self.live().values():
            if core.owns_vehicle(vehicle_id):
                core.on_ack(vehicle_id, plan_id, version, status, now_s)

    def owners(self) -> dict[str, list[int]]:
        """Vehicle -> the shards holding it (the invariant: one each)."""
        out: dict[str, list[int]] = {}
        for r, core in self.live().items():
            for vid in core.book.vehicles():
                out.setdefault(vid, []).append(r)
        return out

    def timing(self) -> dict[str, Any]:
        """Per shard: its work per step (map updates + plans) p50 / p95 ms, and its total s."""
        out = {}
        for r, ms in sorted(self.step_ms.items()):
            a = np.asarray(ms)
            out[str(r)] = {"p50_ms": float(np.percentile(a, 50)), "p95_ms": float(np.percentile(a, 95)),
                           "busy_s": float(a.sum() / 1e3)}  # fmt: skip
        return out

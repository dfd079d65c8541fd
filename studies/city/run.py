"""One run of the city-scale study: a SUMO district (sim/sumo) under one arm, lock step, no rendering.

Arms (what routes the vehicles; those that keep their routes, `SumoWorld.kept`, are left alone by all):
  as_given      the routes the demand came with (a scenario's own; on a generated grid duarouter's)
  shortest      free-flow shortest paths: each vehicle rerouted once as it departs on free-flow times
  sumo_oracle   SUMO's rerouting device: every vehicle rerouted every `reroute_period_s` on every
                edge's live speed (global, perfect information: the oracle baseline)
  sumo_covered  SUMO's router fed only the covered lanes' travel times (moving average like the
                device's), every vehicle rerouted every `reroute_period_s`: the information the
                roadside agents have, routed SUMO's way
  rmmdet        the production `CoordinatorCore`: roadside agents' object lists drawn from the fitted
                perception model (studies/experiments/oracle.py, each agent with `profile`'s errors),
                maps every `map_period_s`, plans on request and pushed, followed by the vehicles'
                plan clients (sim/sumo/clients.py)
Measured: the tripinfo summary (travel time with departure delay, trips per hour), plan counters, and
the coordinator's map + plan time per step (p50 / p95) and CPU seconds per simulated second.
Units: SUMO metres and seconds; the coordinator's side is in table metres (sim/sumo/scene.py).
"""

from __future__ import annotations

import logging
import time
from collections import Counter, deque
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from shared.config import with_overrides
from shared.scene.road_network import RoadNetwork
from shared.timebase import NS_PER_S
from shared.traffic.config import CoordinatorSettings
from shared.traffic.core import RequestRejected
from shared.traffic.regions import RegionMap, partition_junctions
from sim.sumo import trips
from sim.sumo.clients import SumoPlanClients
from sim.sumo.network import TABLE_SCALE
from sim.sumo.scene import UNCOVERED_AREA, RoadsideLayout, scene_from_sumo
from sim.sumo.world import KeptVehicles, Rerouting, SumoWorld
from studies.city.shards import ShardedCoordinator
from studies.experiments.oracle import OracleAgents, OracleErrorModel

log = logging.getLogger(__name__)

ARMS = ("as_given", "shortest", "sumo_oracle", "sumo_covered", "rmmdet")


@dataclass(frozen=True)
class CityRun:
    """What one run drives: `net` with the vehicles of `routes` (and `additional` files: vTypes, signal
    programs, detectors, stops) from `begin_s` for `duration_s` (or until all arrived), roadside agents
    per `layout`."""

    net: Path
    routes: Path | tuple[Path, ...]
    layout: RoadsideLayout
    seed: int
    duration_s: float
    step_s: float = 1.0
    map_period_s: float = 1.0
    reroute_period_s: float = 60.0
    adaptation_steps: int = 180  # samples (one per step) averaged into an edge's travel time
    request_before_m: float = 1.0  # table metres before a lane's end at which a vehicle asks
    profile: str = "agent1"  # the fitted agent whose perception errors every roadside agent has
    max_vehicles: int = 10_000  # plans tracked at once by each coordinator shard
    shards: int = 1  # coordinator regions (studies/city/shards.py)
    kill_shard: int | None = None  # a shard to kill at `kill_at_s` ...
    kill_at_s: float = 0.0
    restart_after_s: float | None = None  # ... and restart this much later (None: never)
    additional: tuple[Path, ...] = ()
    begin_s: float | None = None  # SUMO's begin (None: 0)
    scale: float = 1.0  # the demand scaled by SUMO (--scale)
    keep: KeptVehicles = field(default_factory=KeptVehicles)


def roadside_model(model: OracleErrorModel, agents: list[str], profile: str) -> OracleErrorModel:
    """`model` with every one of `agents` given the fitted errors of `profile`."""
    if profile not in model.agents:
        raise ValueError(f"perception profile {profile!r} not fitted: {sorted(model.agents)}")
    return model.model_copy(update={"agents": dict.fromkeys(agents, model.agents[profile])})


def run_arm(
    run: CityRun, arm: str, coordinator: CoordinatorSettings, model: OracleErrorModel, out: Path
) -> dict[str, Any]:
    """Drive one arm; its summary (trips, counters, timings), tripinfo written under `out`."""
    if arm not in ARMS:
        raise ValueError(f"unknown arm {arm!r}: one of {ARMS}")
    out.mkdir(parents=True, exist_ok=True)
    tripinfo = out / f"{arm}.tripinfo.xml"
    rerouting = Rerouting(period_s=run.reroute_period_s, adaptation_steps=run.adaptation_steps)
    t0, cpu0 = time.perf_counter(), time.process_time()
    counts: Counter[str] = Counter()
    step_ms: list[float] = []
    vehicle_s = 0.0  # vehicle-seconds on the network
    with SumoWorld(
        run.net,
        run.routes,
        run.seed,
        run.step_s,
        rerouting if arm == "sumo_oracle" else None,
        tripinfo,
        additional=run.additional,
        keep=run.keep,
        begin_s=run.begin_s,
        scale=run.scale,
    ) as world:
        begin_s = world.time_s
        driver = _driver(run, arm, world, coordinator, model)
        while world.time_s < begin_s + run.duration_s and world.expected_vehicles() > 0:
            world.step()
            vehicle_s += world.running() * run.step_s
            if driver is not None:
                t = time.perf_counter()
                driver.step(counts)
                step_ms.append((time.perf_counter() - t) * 1e3)
        end_s = world.time_s
        counts.update(world.counts)
        if isinstance(driver, Coordinated):
            counts.update({f"clients/{k}": n for k, n in driver.clients.counts.items()})
            counts.update({f"shards/{k}": n for k, n in driver.coordinator.counts.items()})
            counts["shards/max_owners"] = driver.max_owners
            counts["shards/plans_kept"] = sum(c.plans_kept for c in driver.coordinator.live().values())
    wall_s, cpu_s = time.perf_counter() - t0, time.process_time() - cpu0
    summary = trips.summarise(tripinfo, begin_s, max(end_s, begin_s + run.step_s))
    return {
        "arm": arm,
        "seed": run.seed,
        "roadside_junctions": list(run.layout.junctions),
        "sim_s": end_s - begin_s,
        "running_mean": vehicle_s / max(end_s - begin_s, 1e-9),
        "trips": asdict(summary),
        "counts": dict(counts),
        "driver_ms": _percentiles(step_ms),
        "shard_ms": driver.coordinator.timing() if isinstance(driver, Coordinated) else {},
        "wall_s": wall_s,
        "cpu_s_per_sim_s": cpu_s / max(end_s - begin_s, 1e-9),
    }


def _percentiles(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"p50": None, "p95": None}
    return {"p50": float(np.percentile(values, 50)), "p95": float(np.percentile(values, 95))}


class FreeFlowRouting:
    """`shortest`: each vehicle that may be routed takes the free-flow shortest path to its destination
    as it departs (SUMO's router, nothing adapted), then keeps it."""

    def __init__(self, world: SumoWorld) -> None:
        import libsumo

        self.libsumo = libsumo
        self.world = world

    def step(self, counts: Counter[str]) -> None:
        for vid in self.world.routable(self.libsumo.simulation.getDepartedIDList()):
            self.world.reroute(vid)


class CoveredRerouting:
    """`sumo_covered`: every step each covered edge's travel time is sampled; every reroute period
    their moving averages go to SUMO's router and every vehicle is rerouted on them."""

    def __init__(self, run: CityRun, world: SumoWorld, covered: list[str]) -> None:
        import libsumo

        self.libsumo = libsumo
        self.world = world
        self.every = max(1, round(run.reroute_period_s / run.step_s))
        self.samples = {e: deque[float](maxlen=run.adaptation_steps) for e in covered}
        self.steps = 0

    def step(self, counts: Counter[str]) -> None:
        for edge, window in self.samples.items():
            window.append(self.libsumo.edge.getTraveltime(edge))
        self.steps += 1
        if self.steps % self.every:
            return
        self.world.adapt_travel_times({e: sum(w) / len(w) for e, w in self.samples.items()})
        for vid in self.world.routable(self.libsumo.vehicle.getIDList()):
            self.world.reroute(vid)
        counts["reroute_rounds"] += 1


class Coordinated:
    """`rmmdet`: the coordinator (its shards) fed by the roadside agents, serving the plan clients."""

    def __init__(
        self, run: CityRun, world: SumoWorld, coordinator: CoordinatorSettings, model: OracleErrorModel
    ) -> None:
        scene, ids = scene_from_sumo(run.net, run.layout)
        settings = with_overrides(coordinator, {"planner": {"seed": run.seed}})
        network = RoadNetwork(scene)  # built once: partition and perception stand-in read the same graph
        regions = RegionMap(partition_junctions(network, run.shards, seed=run.seed))
        self.coordinator = ShardedCoordinator(scene, settings, regions, run.max_vehicles)
        agents = sorted(scene.agents)
        self.oracle = OracleAgents(scene, network, roadside_model(model, agents, run.profile), run.seed)
        self.clients = SumoPlanClients(
            world, ids, [lane.id for lane in scene.spec.lanes], run.request_before_m
        )
        self.world = world
        self.run = run
        self.map_every = max(1, round(run.map_period_s / run.step_s))
        self.steps = 0
        self.max_owners = 0

    def _faults(self, now_s: float) -> None:
        run, shards = self.run, self.coordinator.shards
        if run.kill_shard is None:
            return
        if (
            now_s >= run.kill_at_s
            and shards[run.kill_shard] is not None
            and not self.coordinator.counts["killed"]
        ):
            self.coordinator.kill(run.kill_shard)
        back = run.restart_after_s
        if back is not None and now_s >= run.kill_at_s + back and shards[run.kill_shard] is None:
            self.coordinator.restart(run.kill_shard)

    def step(self, counts: Counter[str]) -> None:
        now_s = self.world.time_s
        now_ns = round(now_s * NS_PER_S)  # lock step: the sim clock is every party's clock
        self._faults(now_s)
        self.clients.sync()
        if self.steps % self.map_every == 0:
            states = self.world.vehicles()
            pos = np.zeros((len(states), 3))
            pos[:, :2] = states.position_m / TABLE_SCALE
            vel = np.zeros((len(states), 3))
            speed = states.speed_mps / TABLE_SCALE
            vel[:, 0], vel[:, 1] = speed * np.cos(states.yaw_rad), speed * np.sin(states.yaw_rad)
            for plan in self.coordinator.update(self.oracle(pos, vel), now_s, now_ns):
                self._deliver(plan, now_s, now_ns, counts, "pushed")
        self.steps += 1
        for end in self.clients.take_plan_ends():
            self.coordinator.on_ack(end.vehicle_id, end.plan_id, end.version, end.status, now_s)
        self.clients.expire(now_ns)
        for req in self.clients.requests():
            try:
                plan = self.coordinator.serve(req, now_s, now_ns)
            except RequestRejected as err:
                counts[f"plans/{err.reason}"] += 1
                continue
            self._deliver(plan, now_s, now_ns, counts, "served")
        self.coordinator.end_step()
        self.max_owners = max([self.max_owners, *map(len, self.coordinator.owners().values())])

    def _deliver(self, plan: Any, now_s: float, now_ns: int, counts: Counter[str], how: str) -> None:
        status = self.clients.offer(plan, now_ns)
        self.coordinator.on_ack(plan.vehicle_id, plan.plan_id, int(plan.version), status, now_s)
        counts[f"plans/{how}"] += 1


def _driver(
    run: CityRun, arm: str, world: SumoWorld, coordinator: CoordinatorSettings, model: OracleErrorModel
) -> FreeFlowRouting | CoveredRerouting | Coordinated | None:
    if arm == "shortest":
        return FreeFlowRouting(world)
    if arm == "sumo_covered":
        scene, ids = scene_from_sumo(run.net, run.layout)
        sumo_of = {v: k for k, v in ids.items()}
        covered = sorted(sumo_of[lane.id] for lane in scene.spec.lanes if lane.area != UNCOVERED_AREA)
        return CoveredRerouting(run, world, covered)
    if arm == "rmmdet":
        return Coordinated(run, world, coordinator, model)
    return None  # as_given, sumo_oracle: SUMO alone

"""`rmmdet experiments flow`: the paper's traffic-flow experiment (Table II), random vs scheduled routes.

Each run drives `vehicles` cars for `duration_s` simulated seconds in lock-step (no wall clock). Every
connected car asks for a plan once per lane, `plan_request_m` before its end (as over the bus), and
the planner answers under one policy:

  random / shortest     no maps needed
  paper_rule, balanced  perceived maps: per-agent object lists (only cars inside an agent's areas, with
                        position / velocity noise and misses like the MECs'), merged across agents,
                        smoothed into lane / area maps every `map_period_s`
  dynamic_ground_truth  the same maps built from ground truth of every lane (SUMO-style rerouting)

One run with the full chain (rendered sensors -> MEC pipelines with the ONNX detectors -> maps ->
plans) checks that the perceived maps behave like the oracle's. Measured per run: arrivals at each of
the 7 junctions (the paper's flow), trips completed, trip travel time (mean, p95), mean vehicle speed,
and a mean-speed grid for the heat maps. Units: metres, seconds, m/s.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.traffic.config import CoordinatorSettings, PolicyName
from shared.traffic.lanes import OFF_LANE
from shared.traffic.maps import AgentObjects, TableGrid, TrafficMapBuilder, TrafficSnapshot, merge_agents
from shared.traffic.planner import LaneConditions, RoutePlanner
from sim.config import SimSettings, TrafficSettings
from sim.experiments.config import FlowExperimentSettings, OraclePerception
from sim.traffic import TrafficSim

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
MAP_POLICIES: dict[str, str] = {  # policy -> source of its maps
    "paper_rule": "perceived",
    "balanced": "perceived",
    "dynamic_ground_truth": "ground_truth",
}
GROUND_TRUTH = "ground_truth"
ObjectSource = Callable[[TrafficSim], list[AgentObjects]]


# --- perception stand-ins ---------------------------------------------------------------------------


def vehicle_state(traffic: TrafficSim) -> tuple[FloatArray, FloatArray]:
    """(N, 3) road-contact positions and (N, 3) velocities of every vehicle."""
    pos = np.array([[v.x, v.y, v.z] for v in traffic.vehicles], float).reshape(-1, 3)
    vel = np.array([v.velocity_mps for v in traffic.vehicles], float).reshape(-1, 3)
    return pos, vel


def ground_truth_objects(traffic: TrafficSim) -> list[AgentObjects]:
    pos, vel = vehicle_state(traffic)
    return [AgentObjects(GROUND_TRUTH, pos, vel, np.full(len(pos), 1e-6))]


class OracleAgents:
    """Each agent reports the cars inside its areas, with noise and misses (`OraclePerception`)."""

    def __init__(self, scene: Scene, cfg: OraclePerception, seed: int) -> None:
        self.scene = scene
        self.cfg = cfg
        self.rng = np.random.default_rng(seed)
        self.agent_of_area: dict[str, list[str]] = {}
        for agent in scene.spec.agents:
            for area in agent.areas:
                self.agent_of_area.setdefault(area, []).append(agent.id)

    def __call__(self, traffic: TrafficSim) -> list[AgentObjects]:
        pos, vel = vehicle_state(traffic)
        seen: dict[str, list[int]] = {a: [] for a in self.scene.agents}
        for i, (x, y, z) in enumerate(pos):
            area = self.scene.area_of(float(x), float(y), float(z))
            for agent in self.agent_of_area.get(area or "", []):
                seen[agent].append(i)
        out = []
        var = self.cfg.position_std_m**2
        for agent, rows in seen.items():
            idx = np.array(rows, dtype=np.int64)
            idx = idx[self.rng.uniform(size=len(idx)) < self.cfg.detection_probability]
            p = pos[idx] + self.rng.normal(0.0, self.cfg.position_std_m, (len(idx), 3))
            v = vel[idx] + self.rng.normal(0.0, self.cfg.velocity_std_mps, (len(idx), 3))
            out.append(AgentObjects(agent, p, v, np.full(len(idx), max(var, 1e-6))))
        return out


# --- one run ----------------------------------------------------------------------------------------


@dataclass
class RunResult:
    policy: str
    vehicles: int
    seed: int
    duration_s: float
    arrivals: dict[int, int]  # junction number -> arrivals (the paper's flow)
    trip_times_s: list[float]
    mean_speed_mps: float
    detours: int
    plans: int
    speed_sum: FloatArray  # heat-map grid (rows, cols): sum of sampled speeds
    speed_samples: FloatArray  # and number of samples
    wall_s: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def total_flow(self) -> int:
        return sum(self.arrivals.values())

    def summary(self) -> dict[str, Any]:
        trips = np.array(self.trip_times_s)
        return {
            "policy": self.policy,
            "vehicles": self.vehicles,
            "seed": self.seed,
            "duration_s": self.duration_s,
            "total_flow": self.total_flow,
            "flow_per_junction": {str(k): v for k, v in sorted(self.arrivals.items())},
            "trips": len(trips),
            "travel_time_mean_s": float(trips.mean()) if len(trips) else None,
            "travel_time_p95_s": float(np.percentile(trips, 95)) if len(trips) else None,
            "mean_speed_mps": self.mean_speed_mps,
            "detours": self.detours,
            "plans": self.plans,
            "wall_s": round(self.wall_s, 1),
            **self.extra,
        }


class HeatGrid:
    """Sum and count of vehicle speeds per cell of a regular grid over the table."""

    def __init__(self, scene: Scene, cell_m: float) -> None:
        self.grid = TableGrid.over(scene, cell_m)
        self.speed_sum = np.zeros(self.grid.shape)
        self.samples = np.zeros(self.grid.shape)

    def add(self, pos: FloatArray, speed: FloatArray) -> None:
        cell = self.grid.cells(pos)
        ok = cell >= 0
        np.add.at(self.speed_sum.reshape(-1), cell[ok], speed[ok])
        np.add.at(self.samples.reshape(-1), cell[ok], 1.0)


class Scheduler:
    """The coordinator's decision loop, in-process: maps from an object source, plans on request."""

    def __init__(
        self,
        scene: Scene,
        network: RoadNetwork,
        coordinator: CoordinatorSettings,
        policy: PolicyName,
        seed: int,
        source: ObjectSource | None,
        live_agents: list[str] | None,
    ) -> None:
        planner_cfg = coordinator.planner.model_copy(update={"seed": seed})
        self.planner = RoutePlanner(scene, network, planner_cfg)
        self.builder = TrafficMapBuilder(scene, network, coordinator.maps)
        self.policy = policy
        self.source = source
        self.live_agents = live_agents
        self.cond = LaneConditions()
        self.plans = 0
        self.map_errors: list[float] = []  # per map update: sum over observed lanes of |perceived - true|
        self.map_truth: list[float] = []  # and the true number of vehicles on those lanes

    def update_maps(self, traffic: TrafficSim, objects: list[AgentObjects] | None = None) -> None:
        """Rebuild the maps from `objects` (default: this scheduler's source; none: no maps)."""
        if objects is None:
            if self.source is None:
                return
            objects = self.source(traffic)
        cfg = self.builder.cfg
        vehicles = merge_agents(objects, cfg.dedup_gate_m, cfg.level_separation_m)
        snap = self.builder.update(vehicles, traffic.time_s, self.live_agents)
        self.cond = LaneConditions.from_snapshot(snap)
        self._score_maps(traffic, snap)

    def _score_maps(self, traffic: TrafficSim, snap: TrafficSnapshot) -> None:
        """Perceived vs true vehicles per observed lane (how good the maps the planner uses are)."""
        pos, vel = vehicle_state(traffic)
        true_lane = self.builder.locator.locate(pos, vel)
        on = true_lane != OFF_LANE
        truth = np.bincount(true_lane[on], minlength=len(snap.lane_ids))
        observed = snap.lane_observed
        self.map_errors.append(float(np.abs(snap.lane_count - truth)[observed].sum()))
        self.map_truth.append(float(truth[observed].sum()))

    def serve(self, traffic: TrafficSim) -> None:
        """Plan for every vehicle that asks now (once per lane, like the bus clients)."""
        for v in traffic.vehicles:
            if not traffic.needs_plan(v):
                continue
            v.planned_lane = v.lane_id
            route = self.planner.plan(v.id, v.lane_id, traffic.routing_destination(v), self.cond, self.policy)
            self.planner.commit(v.id, route)
            version = v.plan_version + 1
            traffic.set_plan(v.id, route.lanes, version, plan_id=str(version))
            self.plans += 1


def traffic_settings(sim: SimSettings, vehicles: int) -> TrafficSettings:
    return TrafficSettings.model_validate(
        {**sim.traffic.model_dump(), "vehicles": vehicles, "route_policy": "plan", "connected_fraction": 1.0}
    )


def make_scheduler(
    scene: Scene,
    network: RoadNetwork,
    coordinator: CoordinatorSettings,
    exp: FlowExperimentSettings,
    policy: PolicyName,
    seed: int,
) -> Scheduler:
    kind = MAP_POLICIES.get(policy)
    if kind == "perceived":
        oracle = OracleAgents(scene, exp.oracle, seed)
        return Scheduler(scene, network, coordinator, policy, seed, oracle, list(scene.agents))
    if kind == GROUND_TRUTH:
        return Scheduler(scene, network, coordinator, policy, seed, ground_truth_objects, None)
    return Scheduler(scene, network, coordinator, policy, seed, None, None)


def run_flow(
    scene: Scene,
    sim: SimSettings,
    coordinator: CoordinatorSettings,
    exp: FlowExperimentSettings,
    policy: PolicyName,
    vehicles: int,
    seed: int,
) -> RunResult:
    """One (policy, fleet size, seed) run with oracle or ground-truth maps."""
    t0 = time.perf_counter()
    network = RoadNetwork(scene)
    traffic = TrafficSim(scene, network, traffic_settings(sim, vehicles), seed, sim.tick_hz)
    scheduler = make_scheduler(scene, network, coordinator, exp, policy, seed)
    return _drive(scene, sim, exp, traffic, scheduler, policy, vehicles, seed, exp.duration_s, t0)


def _drive(
    scene: Scene,
    sim: SimSettings,
    exp: FlowExperimentSettings,
    traffic: TrafficSim,
    scheduler: Scheduler,
    policy: str,
    vehicles: int,
    seed: int,
    duration_s: float,
    t0: float,
    step: Callable[[], list[AgentObjects] | None] | None = None,
) -> RunResult:
    """Drive `duration_s`; `step` advances the world and returns fresh objects when it perceives
    (default: the traffic alone, maps from the scheduler's source)."""
    map_every = max(1, round(exp.map_period_s * sim.tick_hz))
    sample_every = max(1, round(exp.speed_sample_period_s * sim.tick_hz))
    grid = HeatGrid(scene, exp.heat_map_cell_m)
    speed_total, speed_n = 0.0, 0
    latest: list[AgentObjects] | None = None
    for tick in range(round(duration_s * sim.tick_hz)):
        if tick % map_every == 0:
            scheduler.update_maps(traffic, latest)
        scheduler.serve(traffic)
        if step is None:
            traffic.step()
        else:
            latest = step() or latest
        if tick % sample_every == 0:
            pos, _ = vehicle_state(traffic)
            speed = np.array([v.v for v in traffic.vehicles])
            grid.add(pos, speed)
            speed_total += float(speed.sum())
            speed_n += len(speed)
    numbers = {j.id: j.number for j in scene.spec.junctions}
    return RunResult(
        policy=policy,
        vehicles=vehicles,
        seed=seed,
        duration_s=duration_s,
        arrivals={numbers[j]: n for j, n in traffic.arrivals.items()},
        trip_times_s=[t.end_s - t.start_s for t in traffic.trips],
        mean_speed_mps=speed_total / max(speed_n, 1),
        detours=traffic.detours,
        plans=scheduler.plans,
        speed_sum=grid.speed_sum,
        speed_samples=grid.samples,
        wall_s=time.perf_counter() - t0,
        extra=map_quality(scheduler),
    )


def map_quality(scheduler: Scheduler) -> dict[str, Any]:
    """Lane-count error of the maps the planner used, over observed lanes and map updates."""
    if not scheduler.map_truth:
        return {}
    truth = float(np.sum(scheduler.map_truth))
    return {
        "map_updates": len(scheduler.map_truth),
        "lane_count_abs_error_per_update": float(np.mean(scheduler.map_errors)),
        "lane_count_relative_error": float(np.sum(scheduler.map_errors)) / max(truth, 1.0),
    }


# --- the full chain ---------------------------------------------------------------------------------


def run_full_perception(
    scene: Scene,
    sim: SimSettings,
    coordinator: CoordinatorSettings,
    exp: FlowExperimentSettings,
    mec: Any,
) -> RunResult:
    """Closed loop through rendered sensors and the MEC pipelines (ONNX detectors, fusion, tracking):
    each agent's tracks become its object list exactly as the MEC publishes and the coordinator reads
    them (TrackedObjects message -> `agent_objects`)."""
    from shared.perception.decode import FrameDecoder
    from shared.perception.inputs import Status
    from shared.perception.output import tracked_objects_message
    from shared.perception.pipeline import AgentPipeline
    from shared.traffic.messages import agent_objects
    from sim.evaluation.fusion import to_inputs
    from sim.lockstep import LockstepSim

    run = exp.full_perception
    t0 = time.perf_counter()
    settings = sim.model_copy(update={"seed": run.seed, "traffic": traffic_settings(sim, run.vehicles)})
    pipelines = {a: AgentPipeline(scene, a, mec) for a in scene.agents}
    decoders = {a: FrameDecoder() for a in scene.agents}
    for pipeline in pipelines.values():
        pipeline.tick_hz = sim.tick_hz  # the live MEC's camera cadence (on sim ticks)
    kinds = {s.id: s.kind for s in scene.spec.sensors}
    latest = {a: AgentObjects.empty(a) for a in scene.agents}
    min_existence = coordinator.maps.min_existence_probability
    with LockstepSim(scene, settings) as world:
        traffic = world.traffic
        scheduler = Scheduler(scene, traffic.net, coordinator, run.policy, run.seed, None, list(scene.agents))

        def step() -> list[AgentObjects] | None:
            tick = world.step()
            if not tick.captures:
                return None
            by_agent: dict[str, list[Any]] = {}
            for capture in tick.captures:
                by_agent.setdefault(capture.spec.agent, []).append(capture)
            stamp_ns = tick.ground_truth.header.stamp.ToNanoseconds()
            for agent, captures in by_agent.items():
                result = pipelines[agent].process(
                    to_inputs(stamp_ns, tick.ground_truth.header.tick, captures, decoders[agent])
                )
                msg = tracked_objects_message(result, agent, Status.FULL, [], kinds)
                latest[agent] = agent_objects(agent, msg, min_existence)
            return list(latest.values())

        result = _drive(
            scene,
            settings,
            exp,
            traffic,
            scheduler,
            run.policy,
            run.vehicles,
            run.seed,
            run.duration_s,
            t0,
            step,
        )
    result.extra["perception"] = "full"
    return result

"""`rmmdet experiments flow`: the paper's traffic-flow experiment (Table II), random vs scheduled routes.

Each run drives `vehicles` cars for `duration_s` simulated seconds in lock-step (no wall clock). Every
connected car asks for a plan once per lane, `plan_request_m` before its end (as over the bus), and
the planner answers under one arm (`parse_arm`: a policy and the maps it plans on):

  random / shortest     no maps needed
  paper_rule, balanced  perceived maps: per-agent object lists from the oracle (`oracle.py`, its error
                        model fitted on the real chain's output), merged across agents, smoothed into
                        lane / area maps every `map_period_s`
  dynamic_ground_truth  the same maps built from ground truth of every lane (SUMO-style rerouting);
  <policy>@ground_truth also any map-reading policy on those maps

`run_full_perception` drives the real chain instead (rendered sensors -> MEC pipelines with the ONNX
detectors -> maps -> plans). Measured per run: arrivals at each of the 7 junctions (the paper's flow),
trips completed, trip travel time (mean, p95), delay over free flow, distance, mean vehicle speed, and
a mean-speed grid for the heat maps. Units: metres, seconds, m/s.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rmmdet.v1.planning_pb2 import RoutePlan, RouteRequest

from shared.config import with_overrides
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from shared.traffic.config import CoordinatorSettings, PolicyName
from shared.traffic.core import CoordinatorCore, RequestRejected
from shared.traffic.lanes import OFF_LANE
from shared.traffic.maps import AgentObjects, TrafficSnapshot
from sim.config import SimSettings, TrafficSettings
from sim.traffic import TrafficSim
from studies.experiments.config import FlowExperimentSettings, parse_arm
from studies.experiments.oracle import ErrorObserver, OracleAgents, OracleErrorModel

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
SECONDS_PER_HOUR = 3600.0
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
    distance_m: float = 0.0  # driven by all vehicles together
    # Completed trips: (vehicle id, its k-th trip, travel time s, free-flow time s or None for the
    # spawn trip). With per-vehicle trip draws the k-th trip of a vehicle is the same in every policy.
    trips: list[tuple[str, int, float, float | None]] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def total_flow(self) -> int:
        return sum(self.arrivals.values())

    def summary(self) -> dict[str, Any]:
        trips = np.array(self.trip_times_s)
        delays = [t - f for _, _, t, f in self.trips if f is not None]
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
            "trips_per_hour": len(trips) * SECONDS_PER_HOUR / self.duration_s,
            "delay_mean_s": float(np.mean(delays)) if delays else None,
            "distance_m": self.distance_m,
            "mean_speed_mps": self.mean_speed_mps,
            "detours": self.detours,
            "plans": self.plans,
            "wall_s": round(self.wall_s, 1),
            **self.extra,
        }


class HeatGrid:
    """Sum and count of vehicle speeds per cell of a regular grid over the table."""

    def __init__(self, scene: Scene, cell_m: float) -> None:
        self.grid = scene.table_grid(cell_m)
        self.speed_sum = np.zeros(self.grid.shape)
        self.samples = np.zeros(self.grid.shape)

    def add(self, pos: FloatArray, speed: FloatArray) -> None:
        cell = self.grid.cells(pos)
        ok = cell >= 0
        np.add.at(self.speed_sum.reshape(-1), cell[ok], speed[ok])
        np.add.at(self.samples.reshape(-1), cell[ok], 1.0)


class Scheduler:
    """The production coordinator (`CoordinatorCore`) in lock step, with the vehicles as its plan
    clients the way the sim's vehicles are live (services/sim/plans.py): a vehicle asks once per lane
    and acknowledges every plan it is given; at its re-planning cadence the core re-checks the active
    plans and the ones it pushes are delivered and acknowledged too. Only the bus is left out."""

    def __init__(
        self,
        scene: Scene,
        coordinator: CoordinatorSettings,
        policy: PolicyName,
        seed: int,
        source: ObjectSource | None,
        max_vehicles: int,
    ) -> None:
        settings = with_overrides(coordinator, {"planner": {"seed": seed, "policy": policy}})
        self.core = CoordinatorCore(
            scene, settings, max_vehicles, ground_truth=source is ground_truth_objects
        )
        self.source = source
        self.plans = 0  # plans served on request
        self.pushed = 0  # plans pushed after a map update (replanning, coverage changes)
        self.counts: Counter[str] = Counter()  # rejections, acknowledgements
        self.map_errors: list[float] = []  # per map update: sum over observed lanes of |perceived - true|
        self.map_truth: list[float] = []  # and the true number of vehicles on those lanes

    def update_maps(self, traffic: TrafficSim, objects: list[AgentObjects] | None = None) -> None:
        """Feed `objects` (default: this scheduler's source; none: no maps), rebuild the maps, then
        deliver the plans the core pushes on them."""
        if objects is None:
            if self.source is None:
                return
            objects = self.source(traffic)
        now_s = traffic.time_s
        stamp_ns = round(now_s * NS_PER_S)
        for o in objects:
            if not self.core.on_objects(o.agent_id, o, stamp_ns, now_s):
                self.counts["rejected/unknown_agent"] += 1
        self.core.tick(now_s, stamp_ns)  # the live coordinator's loop: map rebuilds, re-plan cadence
        if self.core.snapshot is not None:
            self._score_maps(traffic, self.core.snapshot)
        for plan, _stamp_ns, _first in self.core.due(now_s):
            self.pushed += 1
            self._deliver(traffic, plan, now_s)

    def _score_maps(self, traffic: TrafficSim, snap: TrafficSnapshot) -> None:
        """Perceived vs true vehicles per observed lane (how good the maps the planner uses are)."""
        pos, vel = vehicle_state(traffic)
        true_lane = self.core.builder.locator.locate(pos, vel)
        on = true_lane != OFF_LANE
        truth = np.bincount(true_lane[on], minlength=len(snap.lane_ids))
        observed = snap.lane_observed
        self.map_errors.append(float(np.abs(snap.lane_count - truth)[observed].sum()))
        self.map_truth.append(float(truth[observed].sum()))

    def serve(self, traffic: TrafficSim) -> None:
        """The vehicles' plan ends (completed, left by a detour) acknowledged, as the live vehicles do;
        then every vehicle that asks now (once per lane) sends its request and applies the plan."""
        now_s = traffic.time_s
        for end in traffic.take_plan_ends():
            self.core.on_ack(end.vehicle_id, end.plan_id, end.version, end.status, now_s)
            self.counts[f"acks/{end.status.name.lower()}"] += 1
        for v in traffic.vehicles:
            if not traffic.needs_plan(v):
                continue
            v.planned_lane = v.lane_id  # one request per lane, answered or not
            req = RouteRequest(
                vehicle_id=v.id,
                current_lane_id=v.lane_id,
                lane_progress_m=max(0.0, v.s),
                destination_junction_id=traffic.routing_destination(v),
                current_plan_version=v.plan_version,
            )
            try:
                plan, _stamp_ns = self.core.serve(req, now_s, round(now_s * NS_PER_S))
            except RequestRejected as err:
                self.counts[f"plans/{err.reason}"] += 1
                continue
            self.plans += 1
            self._deliver(traffic, plan, now_s)

    def _deliver(self, traffic: TrafficSim, plan: RoutePlan, now_s: float) -> None:
        """The vehicle applies the plan and acknowledges it with its decision (never stale in lock step:
        a plan is applied the tick it is made)."""
        status = traffic.set_plan(plan.vehicle_id, list(plan.lane_ids), int(plan.version), plan.plan_id)
        self.core.on_ack(plan.vehicle_id, plan.plan_id, int(plan.version), status, now_s)
        self.counts[f"acks/{status.name.lower()}"] += 1


def traffic_overrides(vehicles: int) -> dict[str, Any]:
    """The experiment's traffic: `vehicles` cars, every one connected and following its plans, each
    with its own trip draws (every policy drives the same trips: paired comparisons)."""
    return {
        "vehicles": vehicles,
        "route_policy": "plan",
        "connected_fraction": 1.0,
        "trip_draws": "per_vehicle",
    }


def traffic_settings(sim: SimSettings, vehicles: int) -> TrafficSettings:
    return with_overrides(sim.traffic, traffic_overrides(vehicles))


def make_scheduler(
    scene: Scene,
    coordinator: CoordinatorSettings,
    exp: FlowExperimentSettings,
    arm: str,
    seed: int,
    vehicles: int,
) -> Scheduler:
    """The coordinator for one arm (`parse_arm`): its policy, fed from the maps source it names."""
    policy, kind = parse_arm(arm)
    source: ObjectSource | None = None
    if kind == "perceived":
        oracle = OracleAgents(scene, RoadNetwork(scene), OracleErrorModel.load(exp.oracle_model), seed)
        source = lambda traffic: oracle(*vehicle_state(traffic))  # noqa: E731
    elif kind == GROUND_TRUTH:
        source = ground_truth_objects
    return Scheduler(scene, coordinator, policy, seed, source, vehicles)


def run_flow(
    scene: Scene,
    sim: SimSettings,
    coordinator: CoordinatorSettings,
    exp: FlowExperimentSettings,
    arm: str,
    vehicles: int,
    seed: int,
) -> RunResult:
    """One (arm, fleet size, seed) run with oracle or ground-truth maps."""
    t0 = time.perf_counter()
    network = RoadNetwork(scene)
    traffic = TrafficSim(scene, network, traffic_settings(sim, vehicles), seed, sim.tick_hz)
    scheduler = make_scheduler(scene, coordinator, exp, arm, seed, vehicles)
    return _drive(scene, sim, exp, traffic, scheduler, arm, vehicles, seed, exp.duration_s, t0)


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
    before_map_update: Callable[[], None] | None = None,
) -> RunResult:
    """Drive `duration_s`; `step` advances the world and returns fresh objects when it perceives
    (default: the traffic alone, maps from the scheduler's source); `before_map_update` is called
    at each map update, before it."""
    map_every = max(1, round(exp.map_period_s * sim.tick_hz))
    sample_every = max(1, round(exp.speed_sample_period_s * sim.tick_hz))
    grid = HeatGrid(scene, exp.heat_map_cell_m)
    speed_total, speed_n = 0.0, 0
    latest: list[AgentObjects] | None = None
    for tick in range(round(duration_s * sim.tick_hz)):
        if tick % map_every == 0:
            if before_map_update is not None:
                before_map_update()
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
        trip_times_s=[t.travel_time_s for t in traffic.trips],
        trips=[(t.vehicle_id, t.index, t.travel_time_s, t.free_flow_s) for t in traffic.trips],
        distance_m=traffic.distance_m,
        mean_speed_mps=speed_total / max(speed_n, 1),
        detours=traffic.detours,
        plans=scheduler.plans + scheduler.pushed,
        speed_sum=grid.speed_sum,
        speed_samples=grid.samples,
        wall_s=time.perf_counter() - t0,
        extra={
            **map_quality(scheduler),
            "plans_pushed": scheduler.pushed,
            "plan_counts": dict(scheduler.counts),
        },
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
    vehicles: int,
    seed: int,
    duration_s: float,
    observer: ErrorObserver | None = None,
) -> RunResult:
    """Closed loop through rendered sensors and the MEC pipelines (ONNX detectors, fusion, tracking):
    each agent's tracks become its object list exactly as the MEC publishes and the coordinator reads
    them (TrackedObjects message -> `agent_objects`). `observer` measures those lists against ground
    truth (the oracle's fit). The result's policy is `<policy>@mec`."""
    from shared.perception.core import MecCore
    from shared.traffic.messages import agent_objects
    from sim.lockstep import LockstepSim
    from studies.evaluation.fusion import feed_tick, vehicle_boxes, vehicle_velocities

    policy = exp.full_perception.policy
    t0 = time.perf_counter()
    settings = with_overrides(sim, {"seed": seed, "traffic": traffic_overrides(vehicles)})
    cores = {a: MecCore(scene, a, mec) for a in scene.agents}
    for core in cores.values():
        core.tick_hz = sim.tick_hz  # the live MEC's camera cadence (on sim ticks)
    latest = {a: AgentObjects.empty(a) for a in scene.agents}
    stamp_s: dict[str, float] = {}  # capture instant of each agent's newest list
    min_existence = coordinator.maps.min_existence_probability
    with LockstepSim(scene, settings) as world:
        traffic = world.traffic
        scheduler = Scheduler(scene, coordinator, policy, seed, None, vehicles)

        def step() -> list[AgentObjects] | None:
            tick = world.step()
            if not tick.captures:
                return None
            by_agent: dict[str, list[Any]] = {}
            for capture in tick.captures:
                by_agent.setdefault(capture.spec.agent, []).append(capture)
            gt = tick.ground_truth
            stamp_ns = gt.header.stamp.ToNanoseconds()
            truth: tuple[np.ndarray, np.ndarray] | None = None
            for agent, captures in by_agent.items():
                out = feed_tick(cores[agent], stamp_ns, gt.header.tick, captures)
                if out is None:
                    continue
                latest[agent] = agent_objects(agent, out.message, min_existence)
                stamp_s[agent] = stamp_ns / NS_PER_S
                if observer is not None:
                    if truth is None:
                        boxes, vels = vehicle_boxes(gt), vehicle_velocities(gt)
                        ids = list(boxes)
                        b = np.array([boxes[v] for v in ids]).reshape(-1, 7)
                        contact = np.column_stack([b[:, 0], b[:, 1], b[:, 2] - b[:, 5] / 2])
                        truth = contact, np.array([vels[v] for v in ids]).reshape(-1, 2)
                    observer.objects(latest[agent], *truth)
            return list(latest.values())

        def before_map_update() -> None:
            if observer is not None:
                for s in stamp_s.values():
                    observer.age(traffic.time_s - s)

        result = _drive(
            scene,
            settings,
            exp,
            traffic,
            scheduler,
            f"{policy}@mec",
            vehicles,
            seed,
            duration_s,
            t0,
            step,
            before_map_update,
        )
    result.extra["perception"] = "full"
    return result

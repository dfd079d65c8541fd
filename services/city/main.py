"""A SUMO city as the world of the live system (issue 53 item 3, first part): libsumo steps the scenario
on the clock of record, the roadside agents publish object lists drawn from the fitted perception model
(as the city study's agents do), and the scenario's cars are plan clients of the coordinator over the
bus, through the vehicle library a real car runs.

    python -m services.city prepare --scenario RUN.sumocfg --work .run/city [--coverage 0.5 --seed 1]
    python -m services.coordinator --scene .run/city/scene.yaml --settings .run/city/coordinator.yaml
    python -m services.city run --work .run/city [--speed 1]

`prepare` copies the scenario into `work` (sim/sumo/scenario.py: its detectors write there), places the
roadside agents on its crossings by coverage (signalised first), and writes the scene the coordinator
plans on (`scene.yaml`: the net at 1:18, sim/sumo/scene.py) and the coordinator's settings (the
table's with the district's overrides of deploy/experiments/city.yaml). `run` is the world process:
- the clock: `sim_clock` at `CLOCK_HZ` (sim time moves on between SUMO's steps at the target speed),
  its presence as the sim (the coordinator ends the plans of a world that left);
- each roadside agent: its `objects` (TrackedObjects) every `map_period_s`, and the presence and health
  of the sensors and MEC it stands in for (`StandIns`);
- every car that may be routed (sim/sumo/world.py `KeptVehicles`: buses and the like keep their routes)
  asks once per lane (`SumoPlanClients`); replies and pushed plans are checked (`PlanCheck`: signature,
  TTL, the holder's key), taken as its SUMO route, and acknowledged; a plan's end too.
Units: the bus side is in table metres (the scene), SUMO's in metres (`TABLE_SCALE`).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import sumolib
import yaml
import zenoh
from rmmdet.v1.health_pb2 import HealthLevel, ServiceHealth
from rmmdet.v1.perception_pb2 import PerceptionStatus, TrackedObjects
from rmmdet.v1.planning_pb2 import RoutePlan, RouteResponse
from rmmdet.v1.sim_pb2 import SimClock

from shared.bus import names
from shared.bus.codec import MessageDecoder, encode
from shared.bus.health import NOMINAL
from shared.bus.node import Node, Received
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.bus.streams import get_stream, sensor_group
from shared.config import with_overrides
from shared.logging_setup import ReportTimer
from shared.paths import RUN_DIR
from shared.scene.road_network import RoadNetwork
from shared.scene.scene import Scene
from shared.security.plan_signing import PlanVerifier
from shared.service import exit_process, positive_float, report_interval_s, run_service
from shared.shutdown import GracefulShutdown
from shared.timebase import NS_PER_S
from shared.traffic.config import load_coordinator_settings
from shared.traffic.maps import AgentObjects
from shared.traffic.plans import Ack
from shared.traffic.regions import partition_junctions
from shared.vehicle.config import VehicleSettings
from shared.vehicle.plan_client import Outcome, PlanCheck, VehicleLink
from sim.sumo.clients import SumoPlanClients
from sim.sumo.network import TABLE_SCALE
from sim.sumo.scenario import load_scenario, stage
from sim.sumo.scene import RoadsideLayout, coverage_layout, scene_from_sumo
from sim.sumo.world import KeptVehicles, SumoWorld
from studies.city.config import load_city_settings
from studies.city.run import roadside_model
from studies.experiments.config import DEFAULT_ORACLE_MODEL
from studies.experiments.oracle import OracleAgents, OracleErrorModel

log = logging.getLogger("services.city")

SERVICE, SCOPE = names.SIM, "sim"  # the world holds the sim's place on the bus
CLOCK_HZ = 20.0  # sim_clock samples per wall second (SimTime extrapolates at most 0.05 s)
REPLY_QUEUE = 65536  # replies held between steps
PUSHED_QUEUE = 65536
CITY_FILE = "city.json"  # what `prepare` chose, for `run`
#: An agent's object lists older than this many report periods: STALE; this many: LOST (the table's
#: 0.5 s and 3 s at a MEC's 10 Hz are 5 and 30 periods; a world stepping each second reports each second).
STALE_PERIODS, LOST_PERIODS = 2.5, 6.0
#: The region maps `prepare` writes (deploy/profiles/scene/city.yaml names them).
SHARD_COUNTS = (2, 4)


# --- prepare -----------------------------------------------------------------------------------------


def prepare(
    scenario: Path,
    work: Path,
    coverage: float,
    seed: int,
    range_m: float,
    map_period_s: float = 1.0,
    scale: float = 1.0,
) -> dict[str, Any]:
    """Stage the scenario into `work`, place the agents, write the scene, the coordinator's settings
    and `city.json`; what was chosen. The agents report every `map_period_s` (SUMO's step, not a MEC's
    10 Hz): the coordinator's coverage takes an agent as STALE after `STALE_PERIODS` of them."""
    scn = stage(load_scenario(scenario), work / "scenario")
    layout = coverage_layout(sumolib.net.readNet(str(scn.net)), coverage, seed, range_m)
    scene, _ = scene_from_sumo(scn.net, layout, scene_id="city")
    (work / "scene.yaml").write_text(yaml.safe_dump(scene.spec.model_dump(mode="json"), sort_keys=False))
    network = RoadNetwork(scene)
    for shards in SHARD_COUNTS:  # the region maps of `make up WORLD=city SHARDS=N`
        regions = partition_junctions(network, shards, seed=seed)
        (work / f"regions_{shards}.json").write_text(json.dumps({"regions": regions}, indent=1) + "\n")
    district = load_city_settings().coordinator
    reporting = {
        "coverage": {
            "stale_after_s": STALE_PERIODS * map_period_s,
            "lost_after_s": LOST_PERIODS * map_period_s,
        }
    }
    settings = with_overrides(with_overrides(load_coordinator_settings(), district), reporting)
    settings = settings.model_dump(mode="json")
    settings["scene"] = str(work / "scene.yaml")
    (work / "coordinator.yaml").write_text(yaml.safe_dump(settings, sort_keys=False))
    city = {
        "scenario": str(scenario),
        "config": str(scn.config),
        "junctions": list(layout.junctions),
        "range_m": range_m,
        "seed": seed,
        "map_period_s": map_period_s,
        "scale": scale,
        "begin_s": scn.begin_s,
        "end_s": scn.end_s,
    }
    (work / CITY_FILE).write_text(json.dumps(city, indent=2) + "\n")
    log.info(
        "city prepared in %s: %d roadside agents, %d lanes",
        work,
        len(layout.junctions),
        len(scene.spec.lanes),
    )
    return city


# --- run ---------------------------------------------------------------------------------------------


def tracked_objects(agents: list[AgentObjects], body_m: tuple[float, float, float]) -> list[TrackedObjects]:
    """The roadside agents' perceived cars as the MECs publish them: positions (the box's bottom centre
    on the road), velocities and variances; every box the scene's car (`body_m`: length, width, height)."""
    out = []
    for a in agents:
        msg = TrackedObjects(agent_id=a.agent_id, status=PerceptionStatus.PERCEPTION_STATUS_FULL)
        for k in range(len(a)):
            obj = msg.objects.add(track_id=k + 1, existence_probability=1.0)
            x, y, z = (float(v) for v in a.position_m[k])
            obj.box.center_m.x, obj.box.center_m.y, obj.box.center_m.z = x, y, z + body_m[2] / 2
            obj.box.size_m.x, obj.box.size_m.y, obj.box.size_m.z = body_m
            obj.velocity_mps.x, obj.velocity_mps.y = (float(v) for v in a.velocity_mps[k][:2])
            var = float(a.position_var_m2[k])
            obj.position_covariance_m2.extend([var, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, var])
            obj.box.yaw_rad = float(np.arctan2(obj.velocity_mps.y, obj.velocity_mps.x))
        out.append(msg)
    return out


class StandIns:
    """The roadside agents' sensors and MECs the world stands in for (their object lists come from the
    fitted perception model): each one's presence token and a health queryable answering NOMINAL with
    what stands in, so that `rmmdet health` judges the city's loop like the table's."""

    def __init__(self, node: Node, scene: Scene, profile: str) -> None:
        self.node = node
        self.start = time.monotonic()
        self.message = f"stood in by the city world: the perception model with {profile}'s errors"
        alive, health = get_stream("alive"), get_stream("health")
        self._declared: list[Any] = []
        for agent in sorted(scene.agents):
            kinds = sorted({sensor.kind for sensor in scene.sensors_of(agent)})
            sources = [(names.MEC, agent)] + [(names.SENSOR, sensor_group(agent, kind)) for kind in kinds]
            for service, instance in sources:
                ids = {"scope": agent, "service": service, "instance": instance}
                self._declared.append(node.session.liveliness().declare_token(alive.key(**ids)))
                self._declared.append(
                    node.session.declare_queryable(health.key(**ids), self._answer(agent, service, instance))
                )

    def _answer(self, scope: str, service: str, instance: str) -> Any:
        key = get_stream("health").key(scope=scope, service=service, instance=instance)

        def reply(query: zenoh.Query) -> None:
            report = ServiceHealth(
                service=service,
                instance=instance,
                level=HealthLevel.HEALTH_LEVEL_NOMINAL,
                message=self.message,
                uptime_s=time.monotonic() - self.start,
                pid=os.getpid(),
                loop_age_s=0.0,
            )
            report.header.source_id = f"{scope}/{service}/{instance}"
            report.header.stamp.FromNanoseconds(time.time_ns())
            encoded = encode(report)
            query.reply(key, encoded.payload, encoding=encoded.encoding)

        return reply

    def close(self) -> None:
        for declared in self._declared:
            declared.undeclare()


class _ArrivalStamped(BoundedQueue[Outcome]):
    """Outcomes with the time each arrived (Zenoh's thread): request -> plan is measured to the reply's
    arrival, not to the main loop's next step."""

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self.arrived_s: dict[str, float] = {}

    def put(self, item: Outcome) -> bool:
        self.arrived_s[item.vehicle_id] = time.monotonic()
        return super().put(item)


class Fleet:
    """The plan clients of the world's cars on the bus: a `VehicleLink` per car that asked (closed when
    it arrives), replies and pushes applied on the main loop."""

    def __init__(
        self, node: Node, clients: SumoPlanClients, settings: VehicleSettings, start_ns: int
    ) -> None:
        self.node = node
        self.clients = clients
        self.counters = node.counters
        self.timeout_s = settings.plan_request_timeout_s
        self.check = PlanCheck(
            PlanVerifier.watching(settings.plan_key_source()),
            settings.plan_max_ttl_s,
            node.counters,
            start_ns,
        )
        self.decoder = MessageDecoder(RouteResponse, node.counters)
        self.outcomes = _ArrivalStamped(
            REPLY_QUEUE, OverflowPolicy.DROP_OLDEST, node.counters, "dropped/plan_outcomes"
        )
        self.pushed: BoundedQueue[Received] = BoundedQueue(
            PUSHED_QUEUE, OverflowPolicy.DROP_OLDEST, node.counters, "dropped/pushed_plans"
        )
        node.subscribe_stream("route_plan", queue=self.pushed)  # one subscription hears every push
        self.links: dict[str, VehicleLink] = {}
        self._asked_s: dict[str, float] = {}  # vehicle -> when its open request was sent (monotonic)
        self.latencies_s: list[float] = []  # request -> answer taken, since the last `take_latencies`

    def step(self, stamp_ns: int) -> None:
        for outcome in self.outcomes.drain():
            if outcome.plan is None:
                self.counters.inc(f"plans/{outcome.error}")
            else:
                self.counters.inc("plans/replied")
                asked = self._asked_s.pop(outcome.vehicle_id, None)
                arrived = self.outcomes.arrived_s.pop(outcome.vehicle_id, None)
                if asked is not None and arrived is not None:
                    self.latencies_s.append(arrived - asked)
                self.apply(outcome.plan, stamp_ns)
        for received in self.pushed.drain():
            plan: RoutePlan = received.message
            if (get_stream("route_plan").ids(received.key) or {}).get("vehicle") != plan.vehicle_id:
                self.counters.inc("rejected/plan_key_mismatch")
            elif plan.vehicle_id in self.links and self.check.accept(plan, pushed=True):
                self.counters.inc("plans/pushed_received")
                self.apply(plan, stamp_ns)
        for end in self.clients.take_plan_ends():
            link = self.links.pop(end.vehicle_id, None)
            if link is not None:
                link.acknowledge(end.plan_id, end.version, end.status, "", stamp_ns)
                link.close()
                self.counters.inc(f"acks/{end.status.name.lower()}")
        self.clients.expire(stamp_ns)
        for req in self.clients.requests():
            link = self.links.get(req.vehicle_id)
            if link is None:
                link = self.links[req.vehicle_id] = VehicleLink(
                    self.node, req.vehicle_id, self.timeout_s, self.check, self.decoder, self.outcomes
                )
            self._asked_s[req.vehicle_id] = time.monotonic()  # before sending: the reply may beat this line
            link.request(req, stamp_ns)
            self.counters.inc("plans/requested")
        gone = set(self.links) - {v.bus_id for v in self.clients.vehicles.values()}
        for vehicle_id in gone:  # arrived without a plan to end: nothing to acknowledge
            self.links.pop(vehicle_id).close()
            self._asked_s.pop(vehicle_id, None)

    def take_latencies(self) -> list[float]:
        out, self.latencies_s = self.latencies_s, []
        return out

    def apply(self, plan: RoutePlan, stamp_ns: int) -> None:
        link = self.links.get(plan.vehicle_id)
        if link is None:
            self.counters.inc("rejected/plan_unknown_vehicle")
            return
        status = self.clients.offer(plan, stamp_ns)
        reason = "" if status is Ack.ACCEPTED else "not taken by SUMO or the vehicle"
        link.acknowledge(plan.plan_id, int(plan.version), status, reason, plan.header)
        self.counters.inc(f"acks/{status.name.lower()}")


def run(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    work: Path = args.work
    city = json.loads((work / CITY_FILE).read_text())
    scn = load_scenario(Path(city["config"]))
    scene = Scene.load(work / "scene.yaml")
    network = RoadNetwork(scene)
    _, ids = scene_from_sumo(scn.net, RoadsideLayout(tuple(city["junctions"]), city["range_m"]), "city")
    agents = sorted(scene.agents)
    model = roadside_model(OracleErrorModel.load(DEFAULT_ORACLE_MODEL), agents, args.profile)
    oracle = OracleAgents(scene, network, model, city["seed"])
    settings = VehicleSettings()
    car = scene.spec.vehicle
    body_m = (car.length_m, car.width_m, car.height_m)
    start_ns = time.time_ns()
    with (
        Node(conf, service=SERVICE, instance=args.instance, scope=SCOPE, stop=shutdown.event) as node,
        SumoWorld(
            scn.net, scn.routes, city["seed"], args.step_s, additional=scn.additional, begin_s=scn.begin_s,
            keep=KeptVehicles(), scale=city["scale"],
        ) as world,
    ):  # fmt: skip
        clock_pub = node.publisher("sim_clock")
        object_pubs = {a: node.publisher("objects", agent=a, source_id=f"{a}/mec") for a in agents}
        stand_ins = StandIns(node, scene, args.profile)
        clients = SumoPlanClients(world, ids, [lane.id for lane in scene.spec.lanes], args.request_before_m)
        fleet = Fleet(node, clients, settings, start_ns)
        begin_s = world.time_s
        epoch_ns = start_ns

        def stamp_of(sim_s: float) -> int:  # stamps are the run's start plus sim time
            return epoch_ns + round((sim_s - begin_s) * NS_PER_S)

        def publish_clock(sim_s: float) -> None:
            clock = SimClock(step_s=args.step_s, real_time_factor=1.0, target_speed=args.speed)
            clock.sim_time.FromNanoseconds(stamp_of(sim_s))
            clock_pub.put(clock, stamp_ns=stamp_of(sim_s), epoch=epoch_ns)

        node.health.set_status(
            lambda: (NOMINAL, f"{world.running()} running, {len(fleet.links)} asking, {len(world.kept)} kept")
        )
        next_map_s = begin_s
        report = ReportTimer(report_interval_s(args))
        reported = (begin_s, time.monotonic())  # sim time and wall time of the last report
        wall0 = time.monotonic()
        end_s = city["end_s"]
        while not shutdown.requested and (end_s is None or world.time_s < end_s):
            node.health.beat()
            sim_s = world.step()
            clients.sync()
            stamp_ns = stamp_of(sim_s)
            if sim_s >= next_map_s:
                states = world.vehicles()
                pos = np.zeros((len(states), 3))
                pos[:, :2] = states.position_m / TABLE_SCALE
                vel = np.zeros((len(states), 3))
                speed = states.speed_mps / TABLE_SCALE
                vel[:, 0], vel[:, 1] = speed * np.cos(states.yaw_rad), speed * np.sin(states.yaw_rad)
                for msg in tracked_objects(oracle(pos, vel), body_m):
                    object_pubs[msg.agent_id].put(msg, stamp_ns=stamp_ns, frame_id="world")
                next_map_s = sim_s + city["map_period_s"]
            fleet.step(stamp_ns)
            if report.due():
                plans = {
                    k: v for k, v in node.counters.snapshot().items() if k.startswith(("plans/", "acks/"))
                }
                running, kept, asking = world.running(), len(world.kept), len(fleet.links)
                waits = fleet.take_latencies()
                p50, p95 = (np.percentile(waits, [50, 95]) * 1e3) if waits else (float("nan"), float("nan"))
                rtf = (sim_s - reported[0]) / max(time.monotonic() - reported[1], 1e-9)
                reported = (sim_s, time.monotonic())
                log.info(
                    "t %.0f s: RTF %.2f, %d running, %d kept, %d asking; request->plan p50 %.0f / p95 %.0f "
                    "ms; %s", sim_s, rtf, running, kept, asking, p50, p95, plans,
                )  # fmt: skip
            # Until the next step is due: the clock moves on (the coordinator plans on sim time).
            due = wall0 + (sim_s - begin_s + args.step_s) / args.speed
            while not shutdown.requested:
                left = due - time.monotonic()
                publish_clock(min(sim_s + args.step_s, begin_s + (time.monotonic() - wall0) * args.speed))
                if left <= 0 or shutdown.wait(min(left, 1.0 / CLOCK_HZ)):
                    break
        stand_ins.close()
        for link in fleet.links.values():
            link.close()
        counts = {
            **node.counters.snapshot(),
            **world.counts,
            **{f"clients/{k}": n for k, n in clients.counts.items()},
        }
        log.info("city stopped at %.0f s: %s", world.time_s, json.dumps(counts, sort_keys=True))
    return 0


def main(conf: zenoh.Config, args: argparse.Namespace, shutdown: GracefulShutdown) -> int:
    if args.command == "prepare":
        args.work.mkdir(parents=True, exist_ok=True)
        prepare(
            args.scenario, args.work, args.coverage, args.seed, args.range_m, args.map_period_s, args.scale
        )
        return 0
    return run(conf, args, shutdown)


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("command", choices=("prepare", "run"))
    parser.add_argument("--work", type=Path, default=RUN_DIR / "city", help="the city's folder")
    parser.add_argument("--scenario", type=Path, help="prepare: the SUMO configuration (.sumocfg)")
    parser.add_argument(
        "--coverage", type=float, default=0.5, help="prepare: share of crossings with an agent"
    )
    parser.add_argument(
        "--seed", type=int, default=1, help="prepare: agents' draw, SUMO's and the model's seed"
    )
    parser.add_argument("--range-m", type=positive_float, default=60.0, help="prepare: an agent's range, m")
    parser.add_argument(
        "--scale",
        type=positive_float,
        default=1.0,
        help="prepare: the scenario's demand scaled (SUMO --scale)",
    )
    parser.add_argument("--speed", type=positive_float, default=1.0, help="run: sim seconds per wall second")
    parser.add_argument("--step-s", type=positive_float, default=1.0, help="run: SUMO's step, s")
    parser.add_argument(
        "--map-period-s", type=positive_float, default=1.0, help="prepare: the agents' object lists every, s"
    )
    parser.add_argument(
        "--request-before-m", type=positive_float, default=1.0, help="run: table m before a lane's end"
    )
    parser.add_argument(
        "--profile", default="agent1", help="run: the fitted agent whose errors every agent has"
    )


def cli(argv: list[str] | None = None) -> int:
    return run_service("city", main, description=__doc__ or "", add_args=add_args, argv=argv)


if __name__ == "__main__":
    exit_process(cli())

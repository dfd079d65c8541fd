"""SUMO's vehicles as plan clients, with the decision code a real car runs (`shared.vehicle.follower`):
each asks for a plan once per lane, `request_before_m` before its end, toward its trip's last junction;
an accepted plan becomes its SUMO route from the lane it is on (`SumoWorld.set_route`); a plan past its
TTL is dropped and the vehicle routes itself again on what SUMO's router knows (free flow unless told
otherwise); a vehicle that arrives while following a plan ends it COMPLETED, one whose plan SUMO
refuses answers REJECTED_INVALID. Vehicles that keep their routes (`SumoWorld.kept`) have no client; a
vehicle on an edge outside the scene (one cars may not use) asks nothing until it is back on one. Ids
on the coordinator's side are scene ids (`sim.sumo.scene`) and
bus ids for vehicles (`sim.sumo.ids`: any id SUMO allows, mapped onto the bus's pattern and back).
Units: table metres on the coordinator's side, SUMO metres inside SUMO (`TABLE_SCALE`).
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field

import libsumo
from rmmdet.v1.planning_pb2 import RoutePlan, RouteRequest

from shared.traffic.plans import Ack
from shared.vehicle.follower import PlanFollower
from sim.sumo.ids import VehicleIds
from sim.sumo.network import TABLE_SCALE
from sim.sumo.world import SumoWorld

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PlanEnd:
    """A plan a vehicle stopped following, to acknowledge: COMPLETED (arrived) or REJECTED_INVALID."""

    vehicle_id: str  # its bus id
    plan_id: str
    version: int
    status: Ack


@dataclass
class ClientVehicle:
    id: str  # SUMO's
    bus_id: str  # on the coordinator's side (`sim.sumo.ids`)
    destination: str  # scene junction at the end of its trip
    follower: PlanFollower
    lane: str = ""  # scene lane of the edge it is on (the last one while inside a junction)
    progress_m: float = 0.0  # along that lane, table metres
    remaining_m: float = 0.0  # to the lane's end, table metres
    asked_on: str = ""  # the lane its latest request was made on (one request per lane)
    ended: list[PlanEnd] = field(default_factory=list)


class SumoPlanClients:
    """The plan clients of every vehicle running in `world`; `ids` maps SUMO ids to scene ids, `lanes` are
    the scene's lanes (a real net names nodes and edges alike: `104` may be both)."""

    def __init__(
        self, world: SumoWorld, ids: dict[str, str], lanes: Iterable[str], request_before_m: float
    ) -> None:
        self.world = world
        self.scene_of = ids
        self.sumo_of = {v: k for k, v in ids.items()}
        self.known_lanes = frozenset(lanes)
        self.request_before_m = request_before_m
        self.vehicles: dict[str, ClientVehicle] = {}  # by SUMO id
        self.ids = VehicleIds()
        self.counts: Counter[str] = Counter()
        self._ends: list[PlanEnd] = []

    def sync(self) -> None:
        """Take the world's state after a step: vehicles that departed join, arrived ones leave (ending
        the plan they followed), the others' lanes and progress are read."""
        running = set(libsumo.vehicle.getIDList())
        for vid in [v for v in self.vehicles if v not in running]:
            gone = self.vehicles.pop(vid)
            plan = gone.follower.followed
            if plan is not None:
                self._ends.append(PlanEnd(gone.bus_id, plan.plan_id, int(plan.version), Ack.COMPLETED))
        for vid in self.world.routable(sorted(running)):  # the others keep their routes: no client
            v = self.vehicles.get(vid)
            if v is None:
                last = self.world.route(vid)[-1]
                to_node = libsumo.edge.getToJunction(last)
                v = self.vehicles[vid] = ClientVehicle(
                    vid, self.ids.bus(vid), self.scene_of[to_node], PlanFollower(self.known_lanes)
                )
            edge = libsumo.vehicle.getRoadID(vid)
            if edge.startswith(":"):
                continue  # inside a junction: still on its last lane as far as plans go
            lane = self.scene_of.get(edge)
            if lane not in self.known_lanes:  # an edge cars may not use (a bus lane its class may take)
                v.lane = ""
                continue
            v.lane = lane
            pos_m = libsumo.vehicle.getLanePosition(vid)
            length_m = libsumo.lane.getLength(libsumo.vehicle.getLaneID(vid))
            v.progress_m = pos_m / TABLE_SCALE
            v.remaining_m = max(0.0, length_m - pos_m) / TABLE_SCALE

    def requests(self) -> list[RouteRequest]:
        """The requests of the vehicles that ask now: on a lane they have not asked on, near its end,
        not already arriving (the lane ends at their destination)."""
        out = []
        for v in self.vehicles.values():
            if not v.lane or v.asked_on == v.lane or v.remaining_m > self.request_before_m:
                continue
            v.asked_on = v.lane  # one request per lane, answered or not
            if libsumo.edge.getToJunction(self.sumo_of[v.lane]) == self.sumo_of[v.destination]:
                continue
            out.append(
                RouteRequest(
                    vehicle_id=v.bus_id,
                    current_lane_id=v.lane,
                    lane_progress_m=v.progress_m,
                    destination_junction_id=v.destination,
                    current_plan_version=v.follower.version,
                )
            )
        self.counts["requests"] += len(out)
        return out

    def offer(self, plan: RoutePlan, now_ns: int) -> Ack:
        """The vehicle's answer to `plan` (a reply or a push); an accepted plan is its route from now."""
        v = self.vehicles.get(self.ids.sumo(plan.vehicle_id) or "")
        if v is None:
            self.counts["plans_for_gone_vehicles"] += 1
            return Ack.REJECTED_INVALID
        decision = v.follower.judge(plan, now_ns)
        if decision.status is not Ack.ACCEPTED:
            self.counts[f"answer/{decision.status.name.lower()}"] += 1
            return decision.status
        lanes = list(plan.lane_ids)
        start = lanes.index(v.lane) if v.lane in lanes else -1
        if start < 0 or not self.world.set_route(v.id, [self.sumo_of[lane] for lane in lanes[start:]]):
            self.counts["answer/rejected_invalid"] += 1  # it has moved past the plan, or SUMO refused it
            return Ack.REJECTED_INVALID
        v.follower.answered(plan, Ack.ACCEPTED)
        self.counts["answer/accepted"] += 1
        return Ack.ACCEPTED

    def expire(self, now_ns: int) -> int:
        """Drop the plans past their TTL: each such vehicle routes itself again; how many."""
        n = 0
        for v in self.vehicles.values():
            if v.follower.expired(now_ns) is not None:
                self.world.reroute(v.id)
                n += 1
        self.counts["expired"] += n
        return n

    def take_plan_ends(self) -> list[PlanEnd]:
        ends, self._ends = self._ends, []
        return ends

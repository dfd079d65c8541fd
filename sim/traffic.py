"""Traffic on the sand table: kinematic vehicles with pure-pursuit lane following, IDM car following
and exclusive junctions; trips between random origin/destination junctions; route choice per policy.

Each vehicle is a kinematic bicycle (wheelbase, steering and acceleration of its class in the scene)
steered by pure pursuit toward a point ahead on its path (lane, then junction connector, then next lane)
and sped by the Intelligent Driver Model against the nearest vehicle or stop line ahead along that path.
Junctions are exclusive zones (the paper's node queue, docs/references.md (D.4)): a vehicle asks to
enter `junction_request_m` before its lane ends, is admitted first-come-first-served once the junction
is empty and its exit lane has room for it, and stops at the stop line until then. Gaps, stop lines and
room are measured with each vehicle's own length (a scene may mix classes: cars, vans, trucks;
`SceneSpec.traffic_mix`). Arrivals at each junction are counted (the paper's flow points).
Deterministic: one seeded generator, vehicles updated in id order.
Units: metres, seconds, radians.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from shared.geometry.boxes import bev_iou_matrix
from shared.scene.model import VehicleSpec
from shared.scene.road_network import Path, RoadNetwork
from shared.scene.scale import SiteScale, at_scale
from shared.scene.scene import Scene
from shared.traffic.plans import Ack, vehicle_decision
from sim.config import TrafficSettings, fleet_ids

log = logging.getLogger(__name__)

# Appearance: Deepracer-like body colours (RGBA); dataset generation may randomise further.
PALETTE_RGBA: tuple[tuple[float, float, float, float], ...] = (
    (0.85, 0.15, 0.15, 1.0),
    (0.15, 0.35, 0.85, 1.0),
    (0.95, 0.75, 0.1, 1.0),
    (0.1, 0.65, 0.3, 1.0),
    (0.95, 0.95, 0.95, 1.0),
    (0.15, 0.15, 0.18, 1.0),
    (0.9, 0.45, 0.1, 1.0),
    (0.55, 0.2, 0.7, 1.0),
    (0.2, 0.75, 0.8, 1.0),
    (0.75, 0.75, 0.78, 1.0),
)
SPAWN_ATTEMPTS = 200
#: Separates the per-vehicle trip generators from the traffic's generator (`trip_draws: per_vehicle`).
TRIP_STREAM = 0x5452
#: Seeds the shuffle of the fleet's classes apart from the traffic's generator, so a scene without a mix
#: draws exactly what it drew before classes existed, and a mix's placement draws do not shift with it.
CLASS_STREAM = 0x434C
SPAWN_SPACING_FACTOR = 2.0  # x the two vehicles' mean length between the centres of spawned vehicles


def fleet_classes(mix: list[tuple[VehicleSpec, float]], count: int, seed: int) -> list[VehicleSpec]:
    """The class of each of `count` vehicles: as near the mix's fractions as whole vehicles allow (each
    class its whole share, the vehicles left over to the largest remainders, ties in the mix's order),
    in an order shuffled by `seed`. One class: no draw at all."""
    if len(mix) == 1:
        return [mix[0][0]] * count
    shares = [fraction * count for _, fraction in mix]
    counts = [math.floor(share) for share in shares]
    # Remainders rounded so that equal shares tie exactly (12 x 0.7 is 8.3999..., 12 x 0.2 2.4000...).
    by_remainder = sorted(range(len(mix)), key=lambda k: (-round(shares[k] - counts[k], 9), k))
    for k in by_remainder[: count - sum(counts)]:
        counts[k] += 1
    classes = [body for (body, _), n in zip(mix, counts, strict=True) for _ in range(n)]
    order = np.random.default_rng([seed, CLASS_STREAM]).permutation(count)
    return [classes[i] for i in order]


@dataclass
class Trip:
    """One completed trip: junction to junction, sim seconds. `index`: the vehicle's k-th trip (0: the
    one it was spawned on, which starts mid-lane and has no free-flow time)."""

    vehicle_id: str
    origin_junction: str
    destination_junction: str
    start_s: float
    end_s: float
    index: int = 0
    free_flow_s: float | None = None  # shortest route at the speed limits, no waiting

    @property
    def travel_time_s(self) -> float:
        return self.end_s - self.start_s


@dataclass(frozen=True)
class PlanEnd:
    """A vehicle stopped following its plan: `status` COMPLETED (its last lane driven) or
    REJECTED_INVALID (a detour left it); acknowledged to the coordinator so that it no longer holds the
    vehicle to the plan's lanes (`shared/traffic/claims.py`) nor counts its load on them."""

    vehicle_id: str
    plan_id: str
    version: int
    status: Ack
    reason: str


@dataclass
class Vehicle:
    id: str
    index: int
    rgba: tuple[float, float, float, float]
    body: VehicleSpec  # its class: size, wheelbase, steering, acceleration
    path: Path
    s: float
    x: float
    y: float
    z: float
    yaw: float
    pitch: float = 0.0
    v: float = 0.0
    yaw_rate: float = 0.0
    lane_id: str = ""
    next_lane: str | None = None
    requested: bool = False
    admitted: bool = False
    releasing: str | None = None  # junction to release once the body has left its connector
    destination: str = ""
    next_destination: str = ""  # drawn ahead, so a plan made before arriving can already aim at it
    origin: str = ""
    trip_start_s: float = 0.0
    trip_start_lane: str | None = None  # the lane that ended at the trip's origin (None: spawned)
    trips_done: int = 0
    arriving: bool = False  # the junction ahead is this trip's destination
    plan: list[str] = field(default_factory=list)  # lanes to take, from a route plan
    plan_version: int = 0
    plan_id: str = ""
    following: bool = False  # on an accepted plan whose end has not been reported (`PlanEnd`)
    planned_lane: str = ""  # lane on which the latest plan was asked for (one request per lane)
    ask_now: bool = False  # ask for a plan at once, wherever on the lane (a coordinator came back)
    connected: bool = True
    requested_at_s: float = 0.0
    detours: int = 0

    @property
    def velocity_mps(self) -> tuple[float, float, float]:
        """World velocity, along the pitched body on the ramps, m/s."""
        v_xy = self.v * math.cos(self.pitch)
        return (v_xy * math.cos(self.yaw), v_xy * math.sin(self.yaw), self.v * math.sin(-self.pitch))


@dataclass(frozen=True)
class Bends:
    """The samples of one path where a vehicle must slow for the bend (`TrafficSim._bends`)."""

    s_m: np.ndarray  # arc length of each sample along the path
    due_m: np.ndarray  # arc length by which its speed must be reached
    speed_sq: np.ndarray  # (lateral acceleration limit / curvature): its speed squared, m²/s²


Occupancy = dict[str, list[tuple[float, Vehicle]]]  # path id -> (progress m, vehicle), rearmost first


class TrafficSim:
    """All vehicles of one scenario; `step()` advances one tick."""

    def __init__(
        self,
        scene: Scene,
        network: RoadNetwork,
        settings: TrafficSettings,
        seed: int,
        tick_hz: float,
        keep_trips: bool = True,
    ) -> None:
        """`keep_trips`: log every completed trip in `trips` (the studies' travel times); a live sim,
        which runs for days, only counts them (`trips_completed`): the log would grow without bound.
        `settings`' sizes, speeds and accelerations left at their defaults are scaled to `scene` (`cfg`
        holds the result; the sand table's are the defaults as written)."""
        settings = at_scale(settings, SiteScale.of(scene.spec))
        self.scene = scene
        self.net = network
        self.cfg = settings
        self.rng = np.random.default_rng(seed)
        self.dt = 1.0 / tick_hz
        self.tick = 0
        self.time_s = 0.0
        # The IDM's max acceleration is the reference class's (scaled with it); each class drives with
        # its own, the same factor above or below it.
        self._reference_accel_mps2 = scene.spec.vehicle.max_accel_mps2
        self.junction_ids = [j.id for j in scene.spec.junctions]
        self.queues: dict[str, list[str]] = {j: [] for j in self.junction_ids}
        self.occupant: dict[str, str | None] = dict.fromkeys(self.junction_ids)
        self.arrivals: dict[str, int] = dict.fromkeys(self.junction_ids, 0)
        self.trips: list[Trip] = []
        self.keep_trips = keep_trips
        self.trips_completed = 0
        self.detours = 0
        self._plan_ends: list[PlanEnd] = []  # since the last `take_plan_ends`
        self.distance_m = 0.0  # driven by all vehicles together
        self._seed = seed
        self._bend_cache: dict[str, Bends] = {}  # path id -> its bends (`curve_lateral_accel_mps2`)
        self._trip_rngs: dict[int, np.random.Generator] = {}
        self.vehicles: list[Vehicle] = []
        self._by_id: dict[str, Vehicle] = {}
        self.circulating = {lane.id for lane in scene.spec.lanes if lane.circulating}
        # Ring metering: entering traffic is held back while the ring is this full, so circulating
        # vehicles always find room ahead (a full ring would gridlock): counted in slots of the fleet's
        # longest class, so that a ring of only those still moves.
        longest_m = max(body.length_m for body, _ in scene.spec.fleet_mix)
        slot_m = longest_m + settings.idm.min_gap_m
        self.ring_capacity = (
            sum(max(1, int(network.lanes[lane].length_m // slot_m)) for lane in self.circulating) - 1
        )
        self._spawn(settings.vehicles)

    # --- setup -----------------------------------------------------------------------------------

    def _spawn(self, count: int) -> None:
        lanes = sorted(self.net.lanes)
        lengths = np.array([self.net.lanes[lane].length_m for lane in lanes])
        usable: dict[str, np.ndarray] = {}  # per class: the length of each lane it may be placed on
        for body, _ in self.scene.spec.fleet_mix:
            margin = self.cfg.junction_request_m + body.length_m
            usable[body.name] = np.maximum(lengths - margin - body.length_m, 0.0)
            if usable[body.name].sum() <= 0:
                raise ValueError(f"no lane is long enough to spawn a {body.name} on")
        bodies = fleet_classes(self.scene.spec.fleet_mix, count, self._seed)
        for index, (vid, body) in enumerate(zip(fleet_ids(count), bodies, strict=True)):
            length = body.length_m
            margin = self.cfg.junction_request_m + length
            p_lane = usable[body.name] / usable[body.name].sum()
            for _ in range(SPAWN_ATTEMPTS):
                lane_id = lanes[int(self.rng.choice(len(lanes), p=p_lane))]
                path = self.net.lanes[lane_id]
                s = float(self.rng.uniform(length, path.length_m - margin))
                clash = any(
                    v.path is path and abs(v.s - s) < self._spawn_spacing_m(v, length) for v in self.vehicles
                ) or self._too_close_to_any(path.position(s), length)
                if not clash:
                    break
            else:
                raise ValueError(f"could not place vehicle {index}: too many vehicles for the network")
            pos = path.position(s)
            connected = bool(self.rng.uniform() < self.cfg.connected_fraction)
            vehicle = Vehicle(
                id=vid,
                index=index,
                rgba=PALETTE_RGBA[index % len(PALETTE_RGBA)],
                body=body,
                path=path,
                s=s,
                x=float(pos[0]),
                y=float(pos[1]),
                z=float(pos[2]),
                yaw=path.heading_at(s),
                lane_id=lane_id,
                origin=self.net.lane_start_junction(lane_id),
                connected=connected,
            )
            vehicle.destination = self._new_destination(vehicle, exclude=self.net.lane_end_junction(lane_id))
            self.vehicles.append(vehicle)
            self._by_id[vid] = vehicle
        for vehicle in self.vehicles:  # after placement, so placement draws do not depend on this
            vehicle.next_destination = self._new_destination(vehicle, exclude=vehicle.destination)

    @staticmethod
    def _spawn_spacing_m(v: Vehicle, length_m: float) -> float:
        """Least centre distance between `v` and a vehicle `length_m` long placed at spawn."""
        return SPAWN_SPACING_FACTOR * ((v.body.length_m + length_m) / 2)

    def _too_close_to_any(self, pos: np.ndarray, length_m: float) -> bool:
        return any(
            math.hypot(v.x - pos[0], v.y - pos[1]) < self._spawn_spacing_m(v, length_m)
            and abs(v.z - pos[2]) < self.cfg.level_separation_m
            for v in self.vehicles
        )

    def _new_destination(self, v: Vehicle, exclude: str) -> str:
        choices = [j for j in self.junction_ids if j != exclude]
        rng = self.rng
        if self.cfg.trip_draws == "per_vehicle":
            rng = self._trip_rngs.setdefault(
                v.index, np.random.default_rng([self._seed, TRIP_STREAM, v.index])
            )
        return choices[int(rng.integers(len(choices)))]

    def free_flow_s(self, from_lane: str, destination: str) -> float:
        """Shortest route (by distance) from the end of `from_lane` to `destination`, driven at the
        speed limits without waiting: connectors and lanes, sim seconds."""
        total, prev = 0.0, from_lane
        for lane_id in self.net.shortest_route(from_lane, destination):
            junction = self.net.lane_end_junction(prev)
            for path in (self.net.connector(junction, prev, lane_id), self.net.lanes[lane_id]):
                total += path.length_m / self._speed_limit(path)
            prev = lane_id
        return total

    # --- public API ------------------------------------------------------------------------------

    def progress_text(self) -> str:
        """Counts so far, for status lines and logs."""
        arrivals = sum(self.arrivals.values())
        return f"{arrivals} junction arrivals, {self.trips_completed} trips, {self.detours} detours"

    def vehicle(self, vehicle_id: str) -> Vehicle:
        return self._by_id[vehicle_id]

    def set_plan(self, vehicle_id: str, lanes: list[str], version: int, plan_id: str = "") -> Ack:
        """Give a vehicle a plan: the lanes to take, listing first the lane it was made on. Only a plan
        newer than the one followed applies (repeats are DUPLICATE, older ones REJECTED_STALE); a vehicle
        that has moved on along the plan since takes it from its current lane; a plan that does not
        continue from where the vehicle is gets REJECTED_INVALID."""
        v = self._by_id[vehicle_id]
        decision = vehicle_decision(v.plan_version, v.plan_id, plan_id, version)
        if decision is not None:
            return decision
        start = v.lane_id if not v.requested else (v.next_lane or v.lane_id)
        if start in lanes:
            lanes = lanes[lanes.index(start) + 1 :]
        if not self.net.is_valid_route(start, lanes):
            return Ack.REJECTED_INVALID
        v.plan = list(lanes)
        v.plan_version = version
        v.plan_id = plan_id
        v.following = True
        return Ack.ACCEPTED

    def drop_plan(self, vehicle_id: str) -> bool:
        """Stop following the vehicle's plan (its TTL ran out): it routes itself again, by the shortest
        route, as without a coordinator. Its version is kept, so the same plan cannot come back. True if
        it had lanes left to follow."""
        v = self._by_id[vehicle_id]
        had = bool(v.plan)
        v.plan.clear()
        v.following = False  # its TTL: the coordinator ends it at the same time
        return had

    def _end_plan(self, v: Vehicle, status: Ack, reason: str) -> None:
        if v.following:
            v.following = False
            self._plan_ends.append(PlanEnd(v.id, v.plan_id, v.plan_version, status, reason))

    def take_plan_ends(self) -> list[PlanEnd]:
        """The plans vehicles stopped following since the last call, for their acknowledgements."""
        ends, self._plan_ends = self._plan_ends, []
        return ends

    def routing_destination(self, v: Vehicle) -> str:
        """The junction a plan made now should aim at: the next trip's when this lane ends the current."""
        if v.path.lane_id is not None and self.net.lane_end_junction(v.lane_id) == v.destination:
            return v.next_destination
        return v.destination

    def needs_plan(self, v: Vehicle) -> bool:
        """A connected vehicle asks for a plan once per lane, `plan_request_m` before the lane's end, or
        at once when told to (`ask_now`; one already committed to a junction asks from its next lane,
        `plan_origin`)."""
        if not v.connected:
            return False
        if v.ask_now:
            return (v.requested and v.next_lane is not None) or (
                v.path.lane_id is not None and not v.requested
            )
        return (
            v.path.lane_id is not None
            and not v.requested
            and v.planned_lane != v.lane_id
            and v.path.length_m - v.s <= self.cfg.plan_request_m
        )

    def plan_origin(self, v: Vehicle) -> tuple[str, float]:
        """Where a plan asked for now starts (lane, progress on it in m): the vehicle's lane, or the lane
        it has committed to at the junction ahead (a plan must continue from there)."""
        if v.requested and v.next_lane is not None:
            return v.next_lane, 0.0
        return v.lane_id, max(0.0, v.s)

    def step(self) -> None:
        """Advance every vehicle by one tick."""
        occupancy = self._occupancy()
        self._request_junctions()
        self._admit(occupancy)
        for v in self.vehicles:
            self._drive(v, occupancy)
            self.distance_m += v.v * self.dt
        self.tick += 1
        self.time_s = self.tick * self.dt

    def overlapping_pairs(self) -> list[tuple[str, str]]:
        """Pairs of vehicles whose bodies overlap (same level): must stay empty."""
        if len(self.vehicles) < 2:
            return []
        boxes = np.array([[v.x, v.y, v.z, *v.body.size_m, v.yaw] for v in self.vehicles])
        # Broad phase: two footprints can only overlap with their centres closer than the mean of their
        # full diagonals, so the exact rotated-box test runs on those few pairs, not on every pair.
        diagonal = np.hypot(boxes[:, 3], boxes[:, 4])
        d = boxes[:, None, :3] - boxes[None, :, :3]
        near = (np.hypot(d[..., 0], d[..., 1]) < (diagonal[:, None] + diagonal[None, :]) / 2) & (
            np.abs(d[..., 2]) < self.cfg.level_separation_m
        )
        pairs = []
        for i, j in zip(*np.nonzero(np.triu(near, k=1)), strict=True):
            if bev_iou_matrix(boxes[i : i + 1], boxes[j : j + 1])[0, 0] > 0:
                pairs.append((self.vehicles[i].id, self.vehicles[j].id))
        return pairs

    # --- junctions -------------------------------------------------------------------------------

    def _choose_next_lane(self, v: Vehicle) -> str:
        options = self.net.successors[v.lane_id]
        if not options:
            raise RuntimeError(f"lane {v.lane_id} is a dead end")
        policy = self.cfg.route_policy
        if policy == "plan" and v.connected and v.plan and v.plan[0] in options:
            return v.plan.pop(0)
        if policy == "random":
            return options[int(self.rng.integers(len(options)))]
        return self.net.shortest_route(v.lane_id, v.destination)[0]

    def _request_junctions(self) -> None:
        for v in self.vehicles:
            if v.path.lane_id is None or v.requested:
                continue
            if v.path.length_m - v.s > self.cfg.junction_request_m:
                continue
            junction = self.net.lane_end_junction(v.lane_id)
            if v.following and not v.plan:  # at the end of the plan's last lane
                self._end_plan(v, Ack.COMPLETED, "last lane driven")
            if junction == v.destination:
                v.arriving = True
                v.destination = v.next_destination
                v.next_destination = self._new_destination(v, exclude=v.destination)
            v.next_lane = self._choose_next_lane(v)
            v.requested = True
            v.requested_at_s = self.time_s
            self.queues[junction].append(v.id)

    def _exit_has_room(self, v: Vehicle, lane_id: str, occ: Occupancy) -> bool:
        """The rearmost vehicle on the lane (if any) has left room for `v` at its start: its rear half
        and `v`'s whole length, and the least gap."""
        on_lane = occ.get(lane_id)
        if not on_lane:
            return True
        s_rear, rear = on_lane[0]
        return s_rear >= rear.body.length_m / 2 + v.body.length_m + self.cfg.idm.min_gap_m

    def _ring_count(self) -> int:
        return sum(
            1
            for o in self.vehicles
            if o.lane_id in self.circulating
            or (o.path.to_lane is not None and o.path.to_lane in self.circulating)
        )

    def _may_enter(self, v: Vehicle, lane_id: str, occ: Occupancy) -> bool:
        if not self._exit_has_room(v, lane_id, occ):
            return False
        entering_ring = lane_id in self.circulating and v.lane_id not in self.circulating
        return not (entering_ring and self._ring_count() >= self.ring_capacity)

    @staticmethod
    def _is_front(v: Vehicle, occ: Occupancy) -> bool:
        """No other vehicle between this one and its lane's stop line."""
        return occ[v.path.id][-1][0] <= v.s

    def _admit(self, occ: Occupancy) -> None:
        """Admit at most one queued vehicle per free junction. Admission moves nobody, so the tick's
        occupancy snapshot stays exact throughout."""
        for junction, queue in self.queues.items():
            if self.occupant[junction] is not None or not queue:
                continue
            # Circulating traffic first, then first come first served.
            ordered = sorted(queue, key=lambda vid: self._by_id[vid].lane_id not in self.circulating)
            for vid in ordered:
                v = self._by_id[vid]
                assert v.next_lane is not None
                if not self._is_front(v, occ):
                    continue
                if not self._may_enter(v, v.next_lane, occ):
                    if self.time_s - v.requested_at_s < self.cfg.detour_after_s:
                        continue
                    detour = [
                        lane for lane in self.net.successors[v.lane_id] if self._may_enter(v, lane, occ)
                    ]
                    if not detour:
                        continue
                    v.next_lane = detour[int(self.rng.integers(len(detour)))]
                    v.plan.clear()  # the plan no longer applies; the coordinator replans
                    self._end_plan(v, Ack.REJECTED_INVALID, "detour: its next lane was blocked")
                    v.detours += 1
                    self.detours += 1
                v.admitted = True
                self.occupant[junction] = vid
                queue.remove(vid)
                break

    # --- driving ---------------------------------------------------------------------------------

    def _occupancy(self) -> Occupancy:
        """Vehicles on each path (lane or connector id), rearmost first."""
        occ: Occupancy = {}
        for v in self.vehicles:
            occ.setdefault(v.path.id, []).append((v.s, v))
        for items in occ.values():
            items.sort(key=lambda item: item[0])
        return occ

    def _route_ahead(self, v: Vehicle) -> list[Path]:
        """Paths the vehicle will drive, starting with its current one, as far as it may go."""
        paths = [v.path]
        if v.path.lane_id is not None:
            if v.admitted and v.next_lane is not None:
                junction = self.net.lane_end_junction(v.lane_id)
                paths.append(self.net.connector(junction, v.lane_id, v.next_lane))
                paths.append(self.net.lanes[v.next_lane])
        else:
            assert v.path.to_lane is not None
            paths.append(self.net.lanes[v.path.to_lane])
        return paths

    def _leader(self, v: Vehicle, paths: list[Path], occ: Occupancy) -> tuple[float, float]:
        """(bumper gap, leader speed) to the nearest obstacle ahead; stop lines are standing obstacles."""
        offset = -v.s
        for k, path in enumerate(paths):
            for s_other, other in occ.get(path.id, []):
                if other is v or (k == 0 and s_other <= v.s):
                    continue
                return offset + s_other - (v.body.length_m + other.body.length_m) / 2, other.v
            offset += path.length_m
            if offset > self.cfg.horizon_m:
                return math.inf, 0.0
        if paths[-1].lane_id is not None and paths[-1] is v.path and not v.admitted:
            return offset - v.body.length_m / 2, 0.0  # stop line at the lane end
        return math.inf, 0.0

    def _idm_accel(self, v: Vehicle, v0: float, gap: float, lead_v: float) -> float:
        p = self.cfg.idm
        a_max = p.max_accel_mps2 * (v.body.max_accel_mps2 / self._reference_accel_mps2)
        free = 1.0 - (v.v / v0) ** p.exponent
        if math.isinf(gap):
            return a_max * free
        if gap <= 1e-3:  # a numerical guard (the IDM term divides by the gap), not a site size
            return -p.max_decel_mps2
        s_star = p.min_gap_m + max(
            0.0,
            v.v * p.time_headway_s + v.v * (v.v - lead_v) / (2 * math.sqrt(a_max * p.comfort_decel_mps2)),
        )
        return max(a_max * (free - (s_star / gap) ** 2), -p.max_decel_mps2)

    def _speed_limit(self, path: Path) -> float:
        lane_ids = [path.lane_id] if path.lane_id is not None else [path.from_lane, path.to_lane]
        limits = [self.scene.lanes[lane].speed_limit_mps for lane in lane_ids if lane is not None]
        return min([self.cfg.max_speed_mps, *limits])

    def _bends(self, path: Path, lateral_mps2: float) -> Bends:
        """The bend samples of `path` that can hold a vehicle below the fleet's top speed (cached).

        Curvature is the heading's change over a window of the pursuit's standstill look-ahead, the
        scale at which a pursuing vehicle follows the path (a polyline's corner, or a lane joining its
        connector, is no bend to it). A pursuer turns toward its target point, a look-ahead ahead: its
        own curvature is the path's about half a look-ahead further on, so each sample's speed is due
        half the look-ahead (at that speed) before it; due at the sample itself, cars entering the
        intersection's 9-12 m turns ran 15 % above the lateral limit, half a look-ahead before, 5 %."""
        cached = self._bend_cache.get(path.id)
        if cached is None:
            heading = np.unwrap(path.heading)
            pursuit = self.cfg.pursuit
            half_m = pursuit.lookahead_min_m / 2
            lo = np.clip(path.s - half_m, 0.0, path.length_m)
            hi = np.clip(path.s + half_m, 0.0, path.length_m)
            turned = np.abs(np.interp(hi, path.s, heading) - np.interp(lo, path.s, heading))
            curvature = turned / np.maximum(hi - lo, 1e-9)  # 1/m; the guard only for a degenerate path
            with np.errstate(divide="ignore"):
                speed_sq = lateral_mps2 / curvature
            binding = speed_sq < self.cfg.max_speed_mps**2  # no vehicle is ever faster
            lead_m = (pursuit.lookahead_min_m + pursuit.lookahead_gain_s * np.sqrt(speed_sq[binding])) / 2
            s_m = path.s[binding]
            cached = Bends(s_m, s_m - lead_m, speed_sq[binding])
            self._bend_cache[path.id] = cached
        return cached

    def _curve_speed(self, v: Vehicle, paths: list[Path], lateral_mps2: float) -> float:
        """The fastest speed now from which the vehicle can slow, at the IDM's comfortable deceleration,
        to sqrt(lateral / curvature) where each bend sample of its route ahead is due (`_bends`), within
        its braking distance from its speed limit (capped at the car-following horizon)."""
        decel = self.cfg.idm.comfort_decel_mps2
        reach_m = min(self._speed_limit(v.path) ** 2 / (2 * decel), self.cfg.horizon_m)
        best_sq = math.inf
        offset = -v.s  # from the vehicle to the start of `path`, m
        for path in paths:
            bends = self._bends(path, lateral_mps2)
            if len(bends.s_m) and offset + float(bends.due_m.min()) <= reach_m:
                due_m = offset + bends.due_m
                ahead = (offset + bends.s_m >= 0.0) & (due_m <= reach_m)
                if ahead.any():
                    room_m = np.maximum(due_m[ahead], 0.0)
                    best_sq = min(best_sq, float(np.min(bends.speed_sq[ahead] + 2 * decel * room_m)))
            offset += path.length_m
        return math.sqrt(best_sq)

    def _target_point(self, paths: list[Path], s: float, ahead_m: float) -> np.ndarray:
        remaining = s + ahead_m
        for path in paths:
            if remaining <= path.length_m:
                return path.position(remaining)
            remaining -= path.length_m
        last = paths[-1]
        # Past the end of what is known: extend along the final heading (keeps steering calm).
        end = last.position(last.length_m)
        h = float(last.heading[-1])
        return end + remaining * np.array([math.cos(h), math.sin(h), 0.0])

    def _drive(self, v: Vehicle, occ: Occupancy) -> None:
        dt = self.dt
        paths = self._route_ahead(v)
        gap, lead_v = self._leader(v, paths, occ)
        accel = self._idm_accel(v, self._speed_limit(v.path), gap, lead_v)
        if self.cfg.curve_lateral_accel_mps2 is not None:
            # Not the IDM's desired speed: its free-road term lets a vehicle run ~30 % above a lowered
            # v0 when braking; held to the braking profile itself, the bend is entered at its speed.
            allowed = self._curve_speed(v, paths, self.cfg.curve_lateral_accel_mps2)
            accel = min(accel, max((allowed - v.v) / dt, -self.cfg.idm.max_decel_mps2))
        v.v = max(0.0, v.v + accel * dt)
        if gap <= 0.0:
            v.v = 0.0
        # Pure pursuit toward a point ahead on the route.
        lookahead = self.cfg.pursuit.lookahead_min_m + self.cfg.pursuit.lookahead_gain_s * v.v
        target = self._target_point(paths, v.s, lookahead)
        alpha = math.atan2(target[1] - v.y, target[0] - v.x) - v.yaw
        alpha = math.remainder(alpha, 2 * math.pi)
        ld = max(math.hypot(target[0] - v.x, target[1] - v.y), 1e-3)  # numerical guard (divides)
        wheelbase_m, max_steer_rad = v.body.wheelbase_m, v.body.max_steer_rad
        steer = math.atan2(2.0 * wheelbase_m * math.sin(alpha), ld)
        steer = min(max(steer, -max_steer_rad), max_steer_rad)
        v.yaw_rate = v.v / wheelbase_m * math.tan(steer)
        v.x += v.v * math.cos(v.yaw) * dt
        v.y += v.v * math.sin(v.yaw) * dt
        v.yaw = math.remainder(v.yaw + v.yaw_rate * dt, 2 * math.pi)
        self._advance(v, v.s + v.v * dt)
        pos = v.path.position(v.s)
        v.z = float(pos[2])
        v.pitch = -math.atan(v.path.grade_at(v.s))

    def _advance(self, v: Vehicle, s_guess: float) -> None:
        window_m = self.cfg.project_window_m
        s_new = v.path.project(np.array([v.x, v.y]), s_guess, window_m)
        while s_guess >= v.path.length_m - 1e-9 and s_new >= v.path.length_m - 1e-6:
            overflow = max(s_guess - v.path.length_m, 0.0)
            if not self._enter_next(v):
                v.s = v.path.length_m
                v.v = 0.0
                return
            s_guess = overflow
            s_new = v.path.project(np.array([v.x, v.y]), overflow, window_m)
        v.s = max(s_new, 0.0)
        if v.releasing is not None and v.path.lane_id is not None and v.s >= v.body.length_m / 2:
            self.occupant[v.releasing] = None
            v.releasing = None

    def _enter_next(self, v: Vehicle) -> bool:
        if v.path.lane_id is not None:
            if not v.admitted or v.next_lane is None:
                return False
            junction = self.net.lane_end_junction(v.lane_id)
            v.path = self.net.connector(junction, v.lane_id, v.next_lane)
            self.arrivals[junction] += 1
            if v.arriving:
                self.trips_completed += 1
                if self.keep_trips:
                    free_flow = None
                    if v.trip_start_lane is not None:
                        free_flow = self.free_flow_s(v.trip_start_lane, junction)
                    self.trips.append(
                        Trip(v.id, v.origin, junction, v.trip_start_s, self.time_s, v.trips_done, free_flow)
                    )
                v.origin, v.trip_start_s, v.arriving = junction, self.time_s, False
                v.trip_start_lane, v.trips_done = v.lane_id, v.trips_done + 1
            return True
        assert v.path.to_lane is not None and v.path.junction_id is not None
        v.releasing = v.path.junction_id
        v.lane_id = v.path.to_lane
        v.path = self.net.lanes[v.lane_id]
        v.next_lane, v.requested, v.admitted = None, False, False
        return True

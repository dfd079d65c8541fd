"""The coordinator's state and decisions, without the bus (unit-testable, benchmarked in-process).

    on_objects / on_presence   the latest objects of each agent, and its coverage (LIVE/STALE/LOST)
    update_map                 merge the LIVE agents' objects -> smoothed maps -> lane conditions
    serve                      a RouteRequest answered with a plan on the latest maps (RPC), its
                               claims checked against the plan the vehicle follows (claims.py)
    replan / due               re-check active plans; pushed plans to send or resend
    on_ack / receive_ack       delivery bookkeeping from the vehicles' acknowledgements
    tick                       the loop's cadence: coverage changes, map rebuilds and publications,
                               re-planning (what the service does each turn of its loop)

Only LIVE agents' objects enter the maps: a STALE agent's last list no longer describes its area, and
the lanes it covers turn unobserved (count unknown) instead of keeping ghosts. Every plan records
which agents were missing when it was made, so a coverage change can be pushed to the vehicles.

Thread safety: every public method takes the core's lock (the RPC handler runs on a Zenoh thread,
everything else on the service's main thread). Times: `now_s` in seconds on the clock of record (sim
time when a sim runs, shared/timebase.py), wall-clock `wall_ns`.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass

from rmmdet.v1.common_pb2 import ErrorCode
from rmmdet.v1.perception_pb2 import TrackedObjects
from rmmdet.v1.planning_pb2 import RouteAck, RoutePlan, RouteRequest
from rmmdet.v1.traffic_pb2 import TrafficMap

from shared.bus.health import DEGRADED, NOMINAL
from shared.bus.ordering import OrderGate
from shared.bus.streams import limits, validate_id
from shared.scene.scale import SiteScale, at_scale
from shared.scene.scene import Scene
from shared.timebase import NS_PER_S
from shared.traffic import messages
from shared.traffic.claims import Claim, Given, claim_problem, followed_rest, repeats
from shared.traffic.config import CoordinatorSettings
from shared.traffic.coverage import AgentState, CoverageTracker
from shared.traffic.lanes import lane_network
from shared.traffic.maps import AgentObjects, TrafficMapBuilder, TrafficSnapshot, merge_agents
from shared.traffic.planner import (
    ONE_JUNCTION_POLICIES,
    LaneConditions,
    NoRouteError,
    Route,
    RoutePlanner,
    ShardView,
)
from shared.traffic.plans import Ack, ActivePlan, Handover, IssuedPlan, PlanBook, version_of
from shared.traffic.regions import Clique

log = logging.getLogger(__name__)

CLAIM_LOG_FIRST, CLAIM_LOG_EVERY = 10, 100  # refused claims logged: the first ten, then every 100th
GROUND_TRUTH = "ground_truth"  # the oracle object source of studies (every lane observed)
#: Acknowledgements after which the vehicle no longer follows the plan (its lanes are no load).
ENDED = (Ack.REJECTED_INVALID, Ack.REJECTED_STALE, Ack.COMPLETED)
_ACK_STATUS = {a.value: a for a in Ack}  # wire value -> Ack


class RequestRejected(Exception):
    """A route request that cannot be served; `reason` names the rejection counter."""

    def __init__(self, reason: str, code: ErrorCode.ValueType, message: str) -> None:
        super().__init__(message)
        self.reason = reason
        self.code = code
        self.message = message


@dataclass(frozen=True)
class Tick:
    """What one `CoordinatorCore.tick` decided."""

    coverage: dict[str, AgentState] | None  # the agents' states when they changed since the last tick
    publish_map: bool  # the maps are due for publication (period, or a coverage change)
    replanned: int | None  # plans issued by a re-plan (sent by `due`); None when none was due


class CoordinatorCore:
    """The coordinator's decision loop (the service's and the flow experiment's).

    Parameters
    ----------
    scene, settings
        The site and the coordinator settings (`planner.policy` is the policy served). The scene needs
        a lane map (ConfigError otherwise); the settings' sizes and speeds left at their defaults are
        scaled to it (`settings` holds the result; the sand table's are the defaults as written).
    max_vehicles : int
        Vehicles whose plans are tracked at once; a further one evicts the longest idle (`PlanBook.heard`).
    ground_truth : bool
        Studies only: one object source, `GROUND_TRUTH`, that sees every lane (the oracle maps of the
        `dynamic_ground_truth` baseline) instead of the scene's agents and their areas.
    shard : ShardView, optional
        One region of a sharded coordinator (shared/traffic/regions.py): only the agents `shard_agents`
        feed it, it serves only vehicles on lanes it owns ("not_owner" otherwise) and plans over the
        overlay; a vehicle that enters its region comes with its plan (`adopt`, from the last owner's
        `release`).
    """

    def __init__(
        self,
        scene: Scene,
        settings: CoordinatorSettings,
        max_vehicles: int,
        ground_truth: bool = False,
        shard: ShardView | None = None,
        shard_agents: list[str] | None = None,
    ) -> None:
        network = lane_network(scene)
        settings = at_scale(settings, SiteScale.of(scene.spec))
        self.settings = settings
        self.ground_truth = ground_truth
        self.shard = shard
        if ground_truth:
            self.agents = [GROUND_TRUTH]
        else:
            self.agents = list(scene.agents) if shard_agents is None else sorted(shard_agents)
        self.net = network
        self.coverage = CoverageTracker(self.agents, settings.coverage)
        self.builder = TrafficMapBuilder(scene, network, settings.maps)
        self.planner = RoutePlanner(scene, network, settings.planner, shard)
        self.book = PlanBook(settings.delivery, max_vehicles)
        self._lock = threading.Lock()
        self._objects: dict[str, AgentObjects] = {}
        self._stamp_ns: dict[str, int] = {}  # data stamp of each agent's latest objects
        reset_ns = round(limits().order_reset_s * NS_PER_S)
        self._order = {a: OrderGate(reset_ns) for a in self.agents}  # (epoch, stamp) per agent
        self._active: dict[str, ActivePlan] = {}
        self.snapshot: TrafficSnapshot | None = None
        self._cond = LaneConditions()
        self._missing: frozenset[str] = frozenset(self.agents)  # as of the latest maps
        self._map_stamp_ns = 0
        self.dirty = False  # objects arrived since the last map update
        self.next_replan_s: float | None = None  # clock of record; set on the first `replan_if_due`
        self.next_map_s = -math.inf  # clock of record: next periodic map publication (first tick: now)
        self._last_update_s = -math.inf
        self._seen_states = dict.fromkeys(self.agents, AgentState.LOST)  # as of the latest tick
        self.active_count = 0  # active plans, as of the latest re-plan
        self.repeats = 0  # requests answered with the plan their unacknowledged reply carried
        self.claims_refused = 0  # requests refused by `claims.claim_problem`
        self.ended_by_request = 0  # plans ended by a request's `ended_plan_id` before their ack came
        self.plans_kept = 0  # requests answered with the rest of the followed plan (`request_replan`)

    # --- inputs ----------------------------------------------------------------------------------

    def on_objects(
        self, agent: str, objects: AgentObjects, stamp_ns: int, now_s: float, epoch: int = 0
    ) -> bool:
        """Keep `agent`'s latest objects; False for an agent not in the scene (caller counts it).
        Latest wins by (sim run `epoch`, stamp): a list of a new run, or one far behind a bogus newest,
        restarts the order (shared/bus/ordering.py), so one future-stamped list cannot shut out the rest."""
        if agent not in self.coverage.agents:
            return False
        with self._lock:
            if not self._order[agent].admit(epoch, stamp_ns):
                return True  # reordered: the newer list is already held (latest wins)
            self._objects[agent] = objects
            self._stamp_ns[agent] = stamp_ns
            self.coverage.on_data(agent, now_s, len(objects))
            self.dirty = True
        return True

    def receive_objects(
        self, agent: str, msg: TrackedObjects, stamp_ns: int, now_s: float, epoch: int = 0
    ) -> bool:
        """An agent's object list as received (objects below `maps.min_existence_probability` left
        out); False for an agent not in the scene (caller counts it)."""
        if agent not in self.coverage.agents:
            return False
        objects = messages.agent_objects(agent, msg, self.settings.maps.min_existence_probability)
        return self.on_objects(agent, objects, stamp_ns, now_s, epoch)

    def hold_coverage(self, holding: bool, now_s: float) -> None:
        """While `holding` (this process cut off from the bus, or only just back) no agent's coverage
        is demoted (CoverageTracker.hold)."""
        with self._lock:
            self.coverage.hold(holding, now_s)

    def on_presence(self, agent: str, alive: bool) -> bool:
        if agent not in self.coverage.agents:
            return False
        with self._lock:
            self.coverage.on_presence(agent, alive)
        return True

    # --- maps ------------------------------------------------------------------------------------

    def states(self, now_s: float) -> dict[str, AgentState]:
        with self._lock:
            return {a: self.coverage.state(a, now_s) for a in self.agents}

    def update_map(self, now_s: float) -> TrafficSnapshot:
        with self._lock:
            return self._update_map(now_s)

    def _update_map(self, now_s: float) -> TrafficSnapshot:
        live = self.coverage.live(now_s)
        held = [a for a in live if a in self._objects]
        gate_m, level_m = self.settings.maps.dedup_gate_m, self.settings.maps.level_separation_m
        vehicles = merge_agents([self._objects[a] for a in held], gate_m, level_m)
        snap = self.builder.update(vehicles, now_s, None if self.ground_truth else live)
        self.snapshot = snap
        self._cond = LaneConditions.from_snapshot(snap)
        self._missing = frozenset(a for a in self.agents if a not in live)
        self._map_stamp_ns = max((self._stamp_ns[a] for a in held), default=0)
        self.dirty = False
        return snap

    def map_message(self, now_s: float) -> tuple[TrafficMap, int]:
        """The latest maps as a TrafficMap with the current coverage, and their data stamp (0: none)."""
        with self._lock:
            if self.snapshot is None:
                raise RuntimeError("update_map() first")
            coverage = [
                (
                    a,
                    self.coverage.state(a, now_s),
                    self.coverage.age_s(a, now_s),
                    self.coverage.object_count(a),
                )
                for a in self.agents
            ]
            msg = messages.traffic_map(self.snapshot, coverage, self.settings.maps.smoothing_time_constant_s)
            return msg, self._map_stamp_ns

    # --- plans -----------------------------------------------------------------------------------

    def serve(self, req: RouteRequest, now_s: float, wall_ns: int) -> tuple[RoutePlan, int]:
        """Plan for a request (already decoded and range-checked by the codec): the RoutePlan (no
        header) and the data stamp of the maps it was made on. Raises RequestRejected."""
        try:
            validate_id(req.vehicle_id, "vehicle_id")
        except ValueError as err:
            raise RequestRejected("vehicle_id", ErrorCode.ERROR_CODE_INVALID_REQUEST, str(err)) from None
        if req.current_lane_id not in self.net.lanes:
            raise RequestRejected(
                "unknown_lane", ErrorCode.ERROR_CODE_NOT_FOUND, f"unknown lane {req.current_lane_id!r}"
            )
        if req.destination_junction_id not in self.planner.junctions:
            raise RequestRejected(
                "unknown_junction",
                ErrorCode.ERROR_CODE_NOT_FOUND,
                f"unknown junction {req.destination_junction_id!r}",
            )
        if self.shard is not None and not self.shard.owns(req.current_lane_id):
            raise RequestRejected(
                "not_owner",
                ErrorCode.ERROR_CODE_NOT_FOUND,
                f"lane {req.current_lane_id!r} is not in region {self.shard.region}",
            )
        with self._lock:
            if self.dirty or self.snapshot is None:
                # Object lists arrived since the maps were built: a plan uses the newest data (the
                # main loop's rebuilds are rate-limited).
                self._update_map(now_s)
            vid = req.vehicle_id
            for gone in self.book.heard(vid, now_s):
                self._forget(gone)
            claim = Claim(
                req.current_lane_id,
                req.destination_junction_id,
                self.net.lane_start_junction(req.current_lane_id),
            )
            self._end_named_plan(vid, req)
            given = self._given(vid)
            active = self._active.get(vid)
            # The same answer to the same request, unless the coverage it was planned on has changed
            # meanwhile (the new answer says so).
            if active is not None and active.missing == self._missing and repeats(given, claim, wall_ns):
                self.repeats += 1
                return active.message, active.stamp_ns
            problem = claim_problem(given, claim, wall_ns)
            if problem is not None:
                self.claims_refused += 1
                if self.claims_refused <= CLAIM_LOG_FIRST or self.claims_refused % CLAIM_LOG_EVERY == 0:
                    assert given is not None
                    log.warning(
                        "%s refused (%d so far): %s asks from %s to %s, follows %s to %s",
                        problem,
                        self.claims_refused,
                        vid,
                        claim.lane,
                        claim.destination,
                        given.plan.route.lanes,
                        given.destination,
                    )
                raise RequestRejected(
                    problem,
                    ErrorCode.ERROR_CODE_INVALID_REQUEST,
                    f"{vid} follows a plan that does not allow lane {claim.lane!r} to {claim.destination!r}",
                )
            try:
                route = self.planner.plan(vid, req.current_lane_id, req.destination_junction_id, self._cond)
            except NoRouteError as err:
                raise RequestRejected("no_route", ErrorCode.ERROR_CODE_NOT_FOUND, str(err)) from None
            rest = followed_rest(given, claim, wall_ns)
            if (
                self.settings.request_replan == "on_gain"
                and rest is not None
                and active is not None
                and active.missing == self._missing
                and not self._saves(vid, rest, route)
            ):
                route = self.planner.route(vid, rest, self._cond, route.policy)
                self.plans_kept += 1
            plan = self.book.issue(vid, route, now_s, pushed=False, wall_ns=wall_ns)
            msg = self._record(plan, req.destination_junction_id, wall_ns)
            return msg, self._map_stamp_ns

    def _end_named_plan(self, vid: str, req: RouteRequest) -> None:
        """A request repeats the vehicle's last plan-end acknowledgement (`ended_plan_id`, `ended_status`):
        if that plan is still its latest, it ends now, as the ack will end it (the request may have
        overtaken the ack: they travel apart). Caller holds the lock."""
        status = _ACK_STATUS.get(req.ended_status)
        latest = self.book.latest(vid)
        if (
            not req.ended_plan_id
            or status not in ENDED
            or latest is None
            or latest.plan_id != req.ended_plan_id
        ):
            return
        if latest.ack in ENDED:
            return  # the ack came first, as it usually does
        if self.book.on_ack(vid, latest.plan_id, latest.version, status):
            self.planner.forget(vid)
            self.ended_by_request += 1

    def _record(self, plan: IssuedPlan, destination: str, wall_ns: int) -> RoutePlan:
        self.planner.commit(plan.vehicle_id, plan.route)
        valid_until_ns = wall_ns + round(self.settings.planner.plan_ttl_s * NS_PER_S)
        live = [a for a in self.agents if a not in self._missing]
        msg = messages.route_plan(plan, destination, valid_until_ns, live, sorted(self._missing))
        self._active[plan.vehicle_id] = ActivePlan(
            destination, self._missing, msg, self._map_stamp_ns, valid_until_ns
        )
        return msg

    def _given(self, vehicle_id: str) -> Given | None:
        plan, active = self.book.latest(vehicle_id), self._active.get(vehicle_id)
        if plan is None or active is None:
            return None
        return Given(plan, active.destination, active.valid_until_ns)

    def vehicles_left(self) -> int:
        """The process holding the vehicles left the bus (the sim restarted, or its session was cut):
        their plans end with it, so a restarted run's vehicles are not held to the plans of the last
        (`claims.claim_problem`). A cut session's vehicles ask again when the coordinator reappears to
        them. Returns the number of vehicles forgotten."""
        with self._lock:
            vehicles = self.book.vehicles()
            for vid in vehicles:
                self.book.forget(vid)
                self._forget(vid)
            return len(vehicles)

    def replan(self, now_s: float, wall_ns: int) -> int:
        """Re-check every active plan on the latest maps; issue a pushed plan where a new route from
        the lane the vehicle drives next saves more than `replan_gain` of the expected time, or where
        the coverage changed since the plan was made. Returns the number issued (sent by `due`)."""
        issued = 0
        with self._lock:
            for vid in self.book.vehicles():
                plan = self.book.latest(vid)
                active = self._active.get(vid)
                if plan is None or active is None or not self._replannable(plan, now_s):
                    continue
                route = self._better_route(vid, plan.route, active)
                if route is None:
                    continue
                new = self.book.issue(vid, route, now_s, pushed=True, wall_ns=wall_ns)
                self._record(new, active.destination, wall_ns)
                issued += 1
        return issued

    def replan_if_due(self, now_s: float, wall_ns: int) -> int | None:
        """`replan` every `replan_interval_s` of the clock of record, the first time one interval after
        the first call: the number of plans issued, None when not due yet. Called by `tick` (the service's
        loop and the flow experiment's map updates alike)."""
        interval_s = self.settings.replan_interval_s
        if self.next_replan_s is None:
            self.next_replan_s = now_s + interval_s
        if now_s < self.next_replan_s:
            return None
        self.next_replan_s += interval_s
        if self.next_replan_s <= now_s:  # late by a whole interval or more: no catching up
            self.next_replan_s = now_s + interval_s
        return self.replan(now_s, wall_ns)

    def tick(self, now_s: float, wall_ns: int) -> Tick:
        """One turn of the coordinator's loop at `now_s` (clock of record).

        The maps are rebuilt when the coverage changed, when a publication is due (every
        1 / `map_publish_hz`, restarted by a coverage-change publication) and when object lists
        arrived, at most `service.map_update_max_hz` often; then `replan_if_due`.
        """
        states = self.states(now_s)
        changed = states != self._seen_states
        self._seen_states = states
        publish = changed or now_s >= self.next_map_s
        min_update_s = 1.0 / self.settings.service.map_update_max_hz
        if publish or (self.dirty and now_s - self._last_update_s >= min_update_s):
            self.update_map(now_s)
            self._last_update_s = now_s
        if publish:
            self.next_map_s = now_s + 1.0 / self.settings.map_publish_hz
        replanned = self.replan_if_due(now_s, wall_ns)
        if replanned is not None:
            self.active_count = self.active_plans(now_s)
        return Tick(states if changed else None, publish, replanned)

    def health(self) -> tuple[int, str]:
        """(NOMINAL if every agent is LIVE else DEGRADED, one line naming the missing ones) as of the
        latest tick; reads cached values only, so a health callback on another thread may call it."""
        states = self._seen_states
        missing = [f"{a} {s.value}" for a, s in states.items() if s is not AgentState.LIVE]
        text = f"{len(states) - len(missing)}/{len(states)} agents LIVE, {self.active_count} active plans"
        return (DEGRADED, f"{text}; missing: {', '.join(missing)}") if missing else (NOMINAL, text)

    def _replannable(self, plan: IssuedPlan, now_s: float) -> bool:
        if now_s - plan.issued_s > self.settings.planner.plan_ttl_s or plan.ack in ENDED:
            self.planner.forget(plan.vehicle_id)
            return False
        if plan.pushed and plan.ack is None:
            return False  # still being delivered
        # The vehicle may already have turned onto lanes[1] (it asks 1 m before a lane's end), so the
        # first turn stays and the rest is planned again from there.
        return plan.route.policy not in ONE_JUNCTION_POLICIES and len(plan.route.lanes) >= 2

    def _better_route(self, vid: str, route: Route, active: ActivePlan) -> Route | None:
        head, start = route.lanes[0], route.lanes[1]
        try:
            new = self.planner.plan(vid, start, active.destination, self._cond, route.policy)
        except NoRouteError:
            return None
        if not self._saves(vid, route.lanes[1:], new) and active.missing == self._missing:
            return None
        return self.planner.route(vid, [head, *new.lanes], self._cond, route.policy)

    def _saves(self, vid: str, old_lanes: list[str], new: Route) -> bool:
        """`new` (from the same lane as `old_lanes`) is expected to save more than `replan_gain` of the
        time of `old_lanes` on the current maps."""
        old_s = self.planner.route_time_s(old_lanes, self._cond, new.policy, vid)
        return old_s - new.expected_travel_time_s > self.settings.replan_gain * old_s

    @property
    def plans_given_up(self) -> int:
        """Pushed plans never acknowledged after `delivery.max_sends` sends."""
        return self.book.unacknowledged_dropped

    def due(self, now_s: float) -> list[tuple[RoutePlan, int, bool]]:
        """Pushed plans to send now, marked sent: (plan, data stamp, first send)."""
        out = []
        with self._lock:
            for plan in self.book.due(now_s):
                active = self._active[plan.vehicle_id]
                out.append((active.message, active.stamp_ns, plan.sends == 0))
                self.book.sent(plan, now_s)
        return out

    def on_ack(self, vehicle_id: str, plan_id: str, version: int, status: Ack, now_s: float) -> bool:
        """Record an acknowledgement; False when it is not for the vehicle's latest plan."""
        with self._lock:
            recorded = self.book.on_ack(vehicle_id, plan_id, version, status)
            if recorded:
                for gone in self.book.heard(vehicle_id, now_s):
                    self._forget(gone)
            if recorded and status in ENDED:
                self.planner.forget(vehicle_id)
            return recorded

    # --- shards: handing a vehicle over ---------------------------------------------------------

    def release_problem(self, vehicle_id: str, lane: str, wall_ns: int) -> str | None:
        """Why this core must not hand over `vehicle_id` to a shard that says it now asks from `lane`
        (the refusal's name), or None. While the vehicle follows a plan in force here it can only be on
        that plan's lanes (claims.py): a release asked from any other lane is a forgery's (a shard
        never gives away a vehicle that follows its plan on its own lanes because somebody says so)."""
        with self._lock:
            given = self._given(vehicle_id)
            if given is None:
                return None
            claim = Claim(lane, given.destination, self.net.lane_start_junction(lane))
            return "release_claim_lane" if claim_problem(given, claim, wall_ns) is not None else None

    def release(self, vehicle_id: str) -> Handover | None:
        """Hand the vehicle over: its latest plan and what the core keeps of it leave this core (None
        if it has none); the next owner `adopt`s it, so the vehicle has one owner at a time."""
        with self._lock:
            plan, active = self.book.latest(vehicle_id), self._active.get(vehicle_id)
            version = self.book.version(vehicle_id)
            self.book.forget(vehicle_id)  # held by a plan or only by an adopted version: gone from here
            self._forget(vehicle_id)
            if plan is None or active is None:
                return None
            return Handover(plan, version, active)

    def adopt(self, handover: Handover, now_s: float, wall_ns: int) -> None:
        """Take over a vehicle released by another shard: its version counter carries on here, bounded
        by this core's clock (versions are issue times, `plans.version_of`: one from further ahead than
        the clock skew is refused, ValueError, or every later plan would look stale to the vehicle).
        Its route is not taken: nothing proves another shard made it (a forged handover's detour would
        be signed and served as this shard's), so the vehicle's request is planned afresh here."""
        newest = version_of(wall_ns + round(limits().max_clock_skew_s * NS_PER_S))
        if max(handover.version, handover.plan.version) > newest:
            raise ValueError(
                f"version {max(handover.version, handover.plan.version)} is ahead of this shard's clock "
                f"(at most {newest})"
            )
        with self._lock:
            vid = handover.plan.vehicle_id
            for gone in self.book.heard(vid, now_s):
                self._forget(gone)
            self.book.adopt_version(vid, handover.version)

    def owns_vehicle(self, vehicle_id: str) -> bool:
        return self.book.holds(vehicle_id)

    def clique(self) -> Clique:
        """A shard's crossing times on its latest maps, for the other shards (regions.Clique)."""
        with self._lock:
            return self.planner.clique(self._cond)

    def _forget(self, vehicle_id: str) -> None:
        """Drop an evicted vehicle's plan state (its load on the lanes included)."""
        self._active.pop(vehicle_id, None)
        self.planner.forget(vehicle_id)

    @property
    def vehicles_evicted(self) -> int:
        """Vehicles forgotten: idle past `delivery.vehicle_idle_s`, or the longest idle of a full book."""
        return self.book.evicted

    def receive_ack(self, vehicle: str, ack: RouteAck, now_s: float) -> list[str]:
        """An acknowledgement received on `vehicle`'s ack key; returns the counters it counts under
        (``acks/<status>``, plus ``acks/not_latest`` when it is not for the latest plan; a vehicle id
        other than the key's or an unknown status is rejected)."""
        if ack.vehicle_id != vehicle:
            return ["rejected/ack_vehicle_mismatch"]
        status = _ACK_STATUS.get(ack.status)
        if status is None:
            return ["rejected/ack_status"]
        counted = [f"acks/{status.name.lower()}"]
        if not self.on_ack(vehicle, ack.plan_id, int(ack.version), status, now_s):
            counted.append("acks/not_latest")
        return counted

    def active_plans(self, now_s: float) -> int:
        """Vehicles whose latest plan is within its TTL and not ended."""
        ttl_s = self.settings.planner.plan_ttl_s
        with self._lock:
            plans = [self.book.latest(vid) for vid in self.book.vehicles()]
        return sum(1 for p in plans if p is not None and now_s - p.issued_s <= ttl_s and p.ack not in ENDED)

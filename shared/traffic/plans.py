"""Plan delivery bookkeeping: versions, acknowledgements, resends (coordinator side), and the
vehicle side's decision on a received plan.

Plans are must-deliver: each vehicle's plans carry strictly increasing versions; a pushed plan is resent
until acknowledged (at most `max_sends` times, each wait twice the last up to a ceiling:
`DeliveryConfig.ack_wait_s`); the vehicle applies a plan only if it is newer than the
one it follows, so a repeated or reordered plan changes nothing (idempotent) and is acknowledged as
DUPLICATE or REJECTED_STALE. Times are monotonic seconds.
"""

from __future__ import annotations

import re
import uuid
from dataclasses import dataclass
from enum import Enum

from rmmdet.v1.planning_pb2 import RoutePlan

from shared.bus.streams import limits
from shared.security.plan_signing import PlanVerifier
from shared.timebase import NS_PER_S
from shared.traffic.config import DeliveryConfig
from shared.traffic.planner import Route

PLAN_ID = re.compile(r"[0-9a-f]{32}")  # uuid4 hex, as `PlanBook.issue` makes them


#: Plan versions count microseconds since the Unix epoch (below 2^53 until the year 2255): a plan's
#: version is when it was issued. A restarted coordinator therefore continues above every version it
#: issued before without trusting the version a request claims (a forged claim could push a vehicle's
#: versions to the limit), and a vehicle can tell a plan issued before its own run started (a replay
#: from an earlier run) from a plan of this run with no state kept across runs.
PLAN_VERSION_NS = 1000


def version_of(wall_ns: int) -> int:
    """The plan version of an issue time (Unix ns)."""
    return wall_ns // PLAN_VERSION_NS


class Ack(Enum):
    """Mirrors rmmdet.v1.AckStatus."""

    ACCEPTED = 1
    DUPLICATE = 2
    REJECTED_STALE = 3
    REJECTED_INVALID = 4
    COMPLETED = 5


@dataclass
class IssuedPlan:
    vehicle_id: str
    plan_id: str
    version: int
    route: Route
    issued_s: float
    pushed: bool  # sent unsolicited (needs resends until acknowledged); replies to requests are not
    sends: int = 0
    last_send_s: float = 0.0
    ack: Ack | None = None


@dataclass
class ActivePlan:
    """What the coordinator keeps about a vehicle's latest plan beyond the PlanBook (core.py)."""

    destination: str
    missing: frozenset[str]  # agents not LIVE in the maps the plan was made on
    message: RoutePlan  # as sent; resends repeat it unchanged (idempotent at the vehicle)
    stamp_ns: int  # data stamp of the maps it was made on
    valid_until_ns: int  # wall clock


@dataclass(frozen=True)
class Handover:
    """A vehicle passed between shards: its latest plan, its version counter, the core's record."""

    plan: IssuedPlan
    version: int
    active: ActivePlan


class PlanBook:
    """The latest plan issued to each vehicle, and the acknowledgement state of pushed ones."""

    def __init__(self, cfg: DeliveryConfig, max_vehicles: int) -> None:
        self.cfg = cfg
        self.max_vehicles = max_vehicles
        self._latest: dict[str, IssuedPlan] = {}
        self._version: dict[str, int] = {}
        self._heard_s: dict[str, float] = {}  # last request or acknowledgement, insertion = LRU order
        self._accepted: set[str] = set()  # vehicles that accepted a plan of this book (acknowledged)
        self.unacknowledged_dropped = 0  # pushed plans given up after max_sends
        self.evicted = 0  # vehicles forgotten: idle, or the longest idle when a new one came

    def heard(self, vehicle_id: str, now_s: float) -> list[str]:
        """`vehicle_id` asked or acknowledged at `now_s`. Returns the vehicles forgotten: those idle
        longer than `vehicle_idle_s`, then, while more than `max_vehicles`, the longest idle of those
        that never accepted a plan here, and only when there is none the longest idle of the rest. A
        flood of made-up ids (which ask but never acknowledge) cannot lock a real vehicle out, and
        evicts only its own kind while vehicles that follow plans are within the bound (issue 52
        item 10: 10,000 ids evicted every real vehicle's plan)."""
        self._heard_s.pop(vehicle_id, None)
        self._heard_s[vehicle_id] = now_s
        out = []
        for vid, heard_s in list(self._heard_s.items()):
            if now_s - heard_s <= self.cfg.vehicle_idle_s:
                break  # oldest first: the rest are newer
            if vid != vehicle_id:
                out.append(vid)
        for vid in out:
            self.forget(vid)
        if len(self._heard_s) > self.max_vehicles:
            for accepted in (False, True):  # strangers first
                for vid in list(self._heard_s):
                    if len(self._heard_s) <= self.max_vehicles:
                        break
                    if vid != vehicle_id and (vid in self._accepted) is accepted:
                        out.append(vid)
                        self.forget(vid)
        self.evicted += len(out)
        return out

    def forget(self, vehicle_id: str) -> None:
        self._latest.pop(vehicle_id, None)
        self._version.pop(vehicle_id, None)
        self._heard_s.pop(vehicle_id, None)
        self._accepted.discard(vehicle_id)

    def issue(self, vehicle_id: str, route: Route, now_s: float, *, pushed: bool, wall_ns: int) -> IssuedPlan:
        """The vehicle's next plan, issued at `wall_ns` (Unix ns): its version is the issue time
        (`version_of`), or one above the vehicle's previous version if that is later."""
        version = max(self._version.get(vehicle_id, 0) + 1, version_of(wall_ns))
        self._version[vehicle_id] = version
        plan = IssuedPlan(vehicle_id, uuid.uuid4().hex, version, route, now_s, pushed)
        self._latest[vehicle_id] = plan
        return plan

    def latest(self, vehicle_id: str) -> IssuedPlan | None:
        return self._latest.get(vehicle_id)

    def version(self, vehicle_id: str) -> int:
        """The vehicle's latest version (0: none issued here)."""
        return self._version.get(vehicle_id, 0)

    def adopt_version(self, vehicle_id: str, version: int) -> None:
        """Take over a vehicle's version counter from another shard's book, not its plan: the next plan
        issued here is above it (the caller has called `heard` for the vehicle)."""
        self._version[vehicle_id] = max(version, self._version.get(vehicle_id, 0))

    def holds(self, vehicle_id: str) -> bool:
        """A plan or a version counter of the vehicle is kept here (adopted, not yet planned for)."""
        return vehicle_id in self._latest or vehicle_id in self._version

    def vehicles(self) -> list[str]:
        return list(self._latest)

    def sent(self, plan: IssuedPlan, now_s: float) -> None:
        plan.sends += 1
        plan.last_send_s = now_s

    def on_ack(self, vehicle_id: str, plan_id: str, version: int, status: Ack) -> bool:
        """Record an acknowledgement; False if it is not for the vehicle's latest plan (ignored)."""
        plan = self._latest.get(vehicle_id)
        if plan is None or plan.plan_id != plan_id or plan.version != version:
            return False
        plan.ack = status
        if status is Ack.ACCEPTED:
            self._accepted.add(vehicle_id)
        return True

    def due(self, now_s: float) -> list[IssuedPlan]:
        """Pushed plans to (re)send now: never sent, or unacknowledged past the wait after their last send."""
        out = []
        for plan in self._latest.values():
            if not plan.pushed or plan.ack is not None:
                continue
            if plan.sends == 0 or now_s - plan.last_send_s >= self.cfg.ack_wait_s(plan.sends):
                if plan.sends >= self.cfg.max_sends:
                    plan.ack = Ack.REJECTED_STALE  # give up; the vehicle asks again at its next junction
                    self.unacknowledged_dropped += 1
                    continue
                out.append(plan)
        return out


def vehicle_decision(current_version: int, current_plan_id: str, plan_id: str, version: int) -> Ack | None:
    """Vehicle side: DUPLICATE / REJECTED_STALE for a plan not newer than the one followed, else None
    (the caller then validates the route and answers ACCEPTED or REJECTED_INVALID)."""
    if version == current_version and plan_id == current_plan_id:
        return Ack.DUPLICATE
    if version <= current_version:
        return Ack.REJECTED_STALE
    return None


def plan_problem(
    plan: RoutePlan, verifier: PlanVerifier, now_ns: int, max_ttl_s: float, run_start_ns: int = 0
) -> str | None:
    """Vehicle side, before a plan is considered at all: why it is refused (the rejection counter's
    name), or None. Refused: not signed by a trusted coordinator key (`plan_unsigned`,
    `plan_unknown_key`, `plan_bad_signature`), a malformed plan id (`plan_id`), a version out of range
    (`plan_version`: a reply's plan is not range-checked by the codec), issued before the vehicle's
    run started at `run_start_ns` (Unix ns) less the clock skew allowed (`plan_before_run`: a plan of
    an earlier run replayed, still within its TTL), issued after `now_ns` plus that skew (`plan_future`:
    the version is the issue time, and one far ahead would make every later plan stale), or no TTL / one
    reaching further than `max_ttl_s` from now (`plan_ttl`). Version order and expiry are the vehicle's
    decision after."""
    problem = verifier.problem(plan)
    if problem is not None:
        return f"plan_{problem}"
    if not PLAN_ID.fullmatch(plan.plan_id):
        return "plan_id"
    if not 1 <= plan.version <= limits().max_plan_version:
        return "plan_version"
    skew_ns = round(limits().max_clock_skew_s * NS_PER_S)
    if plan.version < version_of(run_start_ns - skew_ns):
        return "plan_before_run"
    if plan.version > version_of(now_ns + skew_ns):
        return "plan_future"
    if not plan.HasField("valid_until") or plan.valid_until.ToNanoseconds() - now_ns > max_ttl_s * NS_PER_S:
        return "plan_ttl"
    return None

"""One real vehicle's decisions on the plans it is offered (after `PlanCheck` accepted them): which it
follows, and what it answers the coordinator (shared/traffic/plans.py `vehicle_decision`, the rule
the sim's vehicles follow too).

- a plan past its TTL: REJECTED_STALE ("expired");
- the plan already followed again: DUPLICATE; an older version than the followed one: REJECTED_STALE;
- a lane the vehicle's road network does not know: REJECTED_INVALID;
- else ACCEPTED, and it is followed until its TTL (`expired`).
A ROS 2 car decides for itself (shared/vehicle/ros2.py): its answer is applied with `answered`.
"""

from __future__ import annotations

from collections.abc import Container
from dataclasses import dataclass

from rmmdet.v1.planning_pb2 import RoutePlan

from shared.traffic.plans import Ack, vehicle_decision


@dataclass(frozen=True)
class Decision:
    status: Ack
    reason: str = ""


class PlanFollower:
    def __init__(self, known_lanes: Container[str]) -> None:
        self.known_lanes = known_lanes
        self.followed: RoutePlan | None = None
        self.version = 0  # the newest version followed: kept after expiry (an older plan stays stale)
        self._followed_id = ""

    def consider(self, plan: RoutePlan, now_ns: int) -> Decision:
        """The vehicle's answer to `plan` (module docstring); an ACCEPTED plan is followed from now."""
        decision = self.judge(plan, now_ns)
        self.answered(plan, decision.status)
        return decision

    def judge(self, plan: RoutePlan, now_ns: int) -> Decision:
        """`consider` without following: what the vehicle would answer."""
        if plan.valid_until.ToNanoseconds() < now_ns:
            return Decision(Ack.REJECTED_STALE, "expired")
        early = vehicle_decision(self.version, self._followed_id, plan.plan_id, int(plan.version))
        if early is not None:
            return Decision(early, "" if early is Ack.DUPLICATE else "older than the plan followed")
        unknown = [lane for lane in plan.lane_ids if lane not in self.known_lanes]
        if unknown:
            return Decision(Ack.REJECTED_INVALID, f"unknown lane {unknown[0]}")
        return Decision(Ack.ACCEPTED)

    def answered(self, plan: RoutePlan, status: Ack) -> None:
        """A car's own answer to `plan`: followed if it accepted it."""
        if status is Ack.ACCEPTED:
            self.followed, self.version, self._followed_id = plan, int(plan.version), plan.plan_id

    def expired(self, now_ns: int) -> RoutePlan | None:
        """The followed plan, once, when its TTL has passed (the vehicle routes itself again)."""
        plan = self.followed
        if plan is not None and plan.valid_until.ToNanoseconds() <= now_ns:
            self.followed = None
            return plan
        return None

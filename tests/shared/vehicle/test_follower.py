"""A real vehicle's decisions on the plans it is offered (shared/vehicle/follower.py)."""

from __future__ import annotations

from rmmdet.v1.planning_pb2 import RoutePlan

from shared.traffic.plans import Ack
from shared.vehicle.follower import Decision, PlanFollower

NOW_NS = 1_790_000_000_000_000_000


def plan(
    version: int, lanes: tuple[str, ...] = ("l0", "l1"), ttl_s: float = 60.0, plan_id: str = ""
) -> RoutePlan:
    p = RoutePlan(
        vehicle_id="v03", plan_id=plan_id or f"{version:032x}", version=version, lane_ids=list(lanes)
    )
    p.valid_until.FromNanoseconds(NOW_NS + int(ttl_s * 1e9))
    return p


def test_decisions() -> None:
    follower = PlanFollower({"l0", "l1", "l2"})
    assert follower.consider(plan(5), NOW_NS) == Decision(Ack.ACCEPTED)
    assert follower.consider(plan(5), NOW_NS) == Decision(Ack.DUPLICATE)
    assert follower.consider(plan(4), NOW_NS).status is Ack.REJECTED_STALE
    assert follower.consider(plan(6, ("l0", "x")), NOW_NS) == Decision(Ack.REJECTED_INVALID, "unknown lane x")
    assert follower.consider(plan(7, ttl_s=-1), NOW_NS) == Decision(Ack.REJECTED_STALE, "expired")
    assert follower.version == 5  # nothing refused is followed
    assert follower.consider(plan(8, ("l2",)), NOW_NS) == Decision(Ack.ACCEPTED)


def test_a_followed_plan_runs_out_once_and_an_older_one_stays_stale() -> None:
    follower = PlanFollower({"l0", "l1"})
    follower.consider(plan(5, ttl_s=1.0), NOW_NS)
    assert follower.expired(NOW_NS) is None
    assert follower.expired(NOW_NS + 2 * 10**9).version == 5
    assert follower.expired(NOW_NS + 3 * 10**9) is None and follower.followed is None
    assert follower.consider(plan(4), NOW_NS).status is Ack.REJECTED_STALE


def test_a_cars_own_answer_is_what_is_followed() -> None:
    follower = PlanFollower(set())  # a car's road network: the car judges the lanes, not this one
    follower.answered(plan(9), Ack.REJECTED_INVALID)
    assert follower.followed is None
    follower.answered(plan(9), Ack.ACCEPTED)
    assert follower.version == 9

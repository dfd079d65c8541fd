"""What a route request may claim about its vehicle, checked against what the coordinator knows.

A RouteRequest names the vehicle's lane, its destination and the plan version it follows; nothing in it
is proven (in the multi-site profile the access control proves only *who* asks: the RPC key names the
vehicle and only its identity may query there). What the coordinator does know is the plan it last gave
the vehicle and whether the vehicle acknowledged following it. While that plan is in force (ACCEPTED or
DUPLICATE, before its `valid_until`), a vehicle following it can only be on one of its lanes, bound for
its destination; on the plan's last lane, or on a lane leaving its destination junction (a vehicle
committed to its next lane asks from there), the trip ends and the next trip's destination may be
asked for. A request claiming anything else is refused and the plan stays as it was, so a forged request
can neither re-route the vehicle nor move the coordinator's record of it (its lane loads, its re-plans).
A vehicle that drives its plan's last lane or leaves the plan on a detour says so (COMPLETED,
REJECTED_INVALID: `sim/traffic.py` `PlanEnd`), which ends the plan here too.

The version a request claims is never trusted (plan versions are issue times, `plans.version_of`).
A request repeating the vehicle's latest request while its reply is unacknowledged (a reply lost in a
router restart, asked again) is answered with the same plan: the same request gets the same answer
(the coordinator plans anew only if the coverage changed meanwhile).
"""

from __future__ import annotations

from dataclasses import dataclass

from shared.traffic.plans import Ack, IssuedPlan

#: Acknowledgements by which the vehicle says it follows the plan.
FOLLOWING = (Ack.ACCEPTED, Ack.DUPLICATE)


@dataclass(frozen=True)
class Claim:
    """What a request says about its vehicle."""

    lane: str
    destination: str
    lane_start_junction: str  # where the claimed lane begins (a trip beyond the plan starts at its end)


@dataclass(frozen=True)
class Given:
    """The vehicle's latest plan as the coordinator gave it."""

    plan: IssuedPlan
    destination: str
    valid_until_ns: int  # wall clock, Unix ns

    def in_force(self, wall_ns: int) -> bool:
        return wall_ns < self.valid_until_ns


def repeats(given: Given | None, claim: Claim, wall_ns: int) -> bool:
    """The request asks again what the latest, still unacknowledged reply answered (same lane and
    destination, within the plan's validity): answer it with that plan."""
    if given is None or given.plan.pushed or given.plan.ack is not None or not given.in_force(wall_ns):
        return False
    return given.plan.route.lanes[0] == claim.lane and given.destination == claim.destination


def claim_problem(given: Given | None, claim: Claim, wall_ns: int) -> str | None:
    """Why the claim contradicts the plan the vehicle follows (the rejection counter's name:
    `claim_lane`, `claim_destination`), or None."""
    if given is None or given.plan.ack not in FOLLOWING or not given.in_force(wall_ns):
        return None
    lanes = given.plan.route.lanes
    if claim.lane in lanes[:-1]:
        return None if claim.destination == given.destination else "claim_destination"
    # On the plan's last lane, or already committed to a lane beyond its destination junction: the
    # trip ends there and the next one may go anywhere.
    if claim.lane == lanes[-1] or claim.lane_start_junction == given.destination:
        return None
    return "claim_lane"


def followed_rest(given: Given | None, claim: Claim, wall_ns: int) -> list[str] | None:
    """The lanes of the plan the vehicle follows from the lane it claims on (that lane first) when the
    claim is on the plan, before its last lane, toward its destination; else None (no plan in force, a
    plan left or finished, another destination)."""
    if given is None or given.plan.ack not in FOLLOWING or not given.in_force(wall_ns):
        return None
    lanes = given.plan.route.lanes
    if claim.destination != given.destination or claim.lane not in lanes[:-1]:
        return None
    return lanes[lanes.index(claim.lane) :]

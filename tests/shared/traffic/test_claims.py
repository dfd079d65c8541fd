"""Route-request claims against the followed plan, and repeated requests: known answers."""

from __future__ import annotations

import pytest

from shared.traffic.claims import Claim, Given, claim_problem, followed_rest, repeats
from shared.traffic.planner import Route
from shared.traffic.plans import Ack, IssuedPlan

# A plan from lane a over b to c, which ends at junction j9; valid until t = 100 ns.
ROUTE = Route(["a", "b", "c"], ["j1", "j2", "j9"], 6.0, 3.0, "shortest")
NOW, LATER = 50, 100


def given(ack: Ack | None, pushed: bool = False) -> Given:
    plan = IssuedPlan("v1", "0" * 32, 7, ROUTE, 0.0, pushed, ack=ack)
    return Given(plan, "j9", valid_until_ns=LATER)


@pytest.mark.parametrize(
    ("claim", "problem"),
    [
        (Claim("a", "j9", "j0"), None),  # where it is, where it goes
        (Claim("b", "j9", "j1"), None),  # further along
        (Claim("b", "j4", "j1"), "claim_destination"),  # mid-plan, elsewhere
        (Claim("c", "j4", "j2"), None),  # on the last lane: the next trip's destination
        (Claim("d", "j4", "j9"), None),  # committed to a lane leaving j9: the next trip
        (Claim("x", "j9", "j5"), "claim_lane"),  # a lane the plan does not hold
    ],
)
def test_a_followed_plan_bounds_the_claims(claim: Claim, problem: str | None) -> None:
    assert claim_problem(given(Ack.ACCEPTED), claim, NOW) == problem
    assert claim_problem(given(Ack.DUPLICATE), claim, NOW) == problem


@pytest.mark.parametrize("ack", [None, Ack.REJECTED_INVALID, Ack.REJECTED_STALE, Ack.COMPLETED])
def test_a_plan_not_followed_bounds_nothing(ack: Ack | None) -> None:
    assert claim_problem(given(ack), Claim("x", "j4", "j5"), NOW) is None


def test_a_lapsed_plan_bounds_nothing_and_no_plan_neither() -> None:
    assert claim_problem(given(Ack.ACCEPTED), Claim("x", "j4", "j5"), LATER) is None
    assert claim_problem(None, Claim("x", "j4", "j5"), NOW) is None


def test_only_an_unacknowledged_reply_to_the_same_request_repeats() -> None:
    same = Claim("a", "j9", "j0")
    assert repeats(given(None), same, NOW)
    assert not repeats(given(None), Claim("b", "j9", "j1"), NOW)  # another lane
    assert not repeats(given(None), Claim("a", "j4", "j0"), NOW)  # another destination
    assert not repeats(given(Ack.ACCEPTED), same, NOW)  # acknowledged: the vehicle has it
    assert not repeats(given(None, pushed=True), same, NOW)  # a push is no answer to a request
    assert not repeats(given(None), same, LATER)  # lapsed
    assert not repeats(None, same, NOW)


@pytest.mark.parametrize(
    ("claim", "ack", "now", "rest"),
    [
        (Claim("a", "j9", "j0"), Ack.ACCEPTED, NOW, ["a", "b", "c"]),
        (Claim("b", "j9", "j1"), Ack.DUPLICATE, NOW, ["b", "c"]),
        (Claim("c", "j9", "j2"), Ack.ACCEPTED, NOW, None),  # the last lane: nothing left to keep
        (Claim("b", "j4", "j1"), Ack.ACCEPTED, NOW, None),  # another destination
        (Claim("x", "j9", "j5"), Ack.ACCEPTED, NOW, None),  # off the plan
        (Claim("b", "j9", "j1"), None, NOW, None),  # not acknowledged: not followed
        (Claim("b", "j9", "j1"), Ack.REJECTED_INVALID, NOW, None),
        (Claim("b", "j9", "j1"), Ack.ACCEPTED, LATER, None),  # lapsed
    ],
)
def test_the_rest_of_a_followed_plan_from_the_claimed_lane(
    claim: Claim, ack: Ack | None, now: int, rest: list[str] | None
) -> None:
    assert followed_rest(given(ack), claim, now) == rest
    assert followed_rest(None, claim, now) is None

"""PlanBook versions, acknowledgements and resends; the vehicle's decision on a received plan."""

from __future__ import annotations

import pytest

from shared.traffic.config import DeliveryConfig
from shared.traffic.planner import Route
from shared.traffic.plans import Ack, PlanBook, vehicle_decision, version_of

ROUTE = Route(["in", "ab"], ["ja"], 4.0, 3.0, "shortest")
WALL_NS = 1_790_000_000_000_000_000  # an issue time, Unix ns (late 2026)


@pytest.fixture
def book() -> PlanBook:
    return PlanBook(DeliveryConfig(ack_timeout_s=0.5, max_sends=3), max_vehicles=16)


def test_versions_increase_per_vehicle(book: PlanBook) -> None:
    v1 = [book.issue("v1", ROUTE, t, pushed=False, wall_ns=WALL_NS).version for t in (0.0, 1.0, 2.0)]
    v2 = [book.issue("v2", ROUTE, 3.0, pushed=True, wall_ns=WALL_NS).version]
    first = version_of(WALL_NS)
    assert v1 == [first, first + 1, first + 2]  # issued within one microsecond: one above the last
    assert v2 == [first]
    latest = book.latest("v1")
    assert latest is not None and latest.version == first + 2
    assert book.latest("nobody") is None
    assert book.vehicles() == ["v1", "v2"]


def test_plan_ids_are_unique(book: PlanBook) -> None:
    ids = {book.issue("v1", ROUTE, 0.0, pushed=False, wall_ns=WALL_NS).plan_id for _ in range(20)}
    assert len(ids) == 20


def test_a_version_is_its_issue_time_in_microseconds_so_a_new_book_continues_above_an_old_one() -> None:
    """A restarted coordinator (a new book) issues versions above every one it issued before, with
    nothing persisted and nothing taken from the request."""
    assert version_of(1_000_999) == 1000 and version_of(WALL_NS) == WALL_NS // 1000
    old = PlanBook(DeliveryConfig(), max_vehicles=4)
    before = [old.issue("v1", ROUTE, 0.0, pushed=False, wall_ns=WALL_NS).version for _ in range(5)]
    later = PlanBook(DeliveryConfig(), max_vehicles=4).issue(
        "v1", ROUTE, 0.0, pushed=False, wall_ns=WALL_NS + 10_000
    )
    assert later.version > max(before)
    assert later.version < 2**53  # within the versions JSON and the validators carry exactly


def test_issue_keeps_the_plan(book: PlanBook) -> None:
    plan = book.issue("v1", ROUTE, 7.5, pushed=True, wall_ns=WALL_NS)
    assert (plan.vehicle_id, plan.route, plan.issued_s, plan.pushed) == ("v1", ROUTE, 7.5, True)
    assert (plan.sends, plan.ack) == (0, None)


def test_on_ack_only_for_the_latest_plan(book: PlanBook) -> None:
    old = book.issue("v1", ROUTE, 0.0, pushed=True, wall_ns=WALL_NS)
    new = book.issue("v1", ROUTE, 1.0, pushed=True, wall_ns=WALL_NS)
    assert not book.on_ack("v1", old.plan_id, old.version, Ack.ACCEPTED)  # superseded plan
    assert not book.on_ack("v1", new.plan_id, old.version, Ack.ACCEPTED)  # wrong version
    assert not book.on_ack("v1", "other", new.version, Ack.ACCEPTED)  # wrong plan id
    assert not book.on_ack("v2", new.plan_id, new.version, Ack.ACCEPTED)  # unknown vehicle
    assert new.ack is None and old.ack is None
    assert book.on_ack("v1", new.plan_id, new.version, Ack.DUPLICATE)
    assert new.ack is Ack.DUPLICATE


def test_due_sends_resends_with_backoff_and_gives_up(book: PlanBook) -> None:
    plan = book.issue("v1", ROUTE, 0.0, pushed=True, wall_ns=WALL_NS)
    assert book.due(0.0) == [plan]  # never sent: due at once
    book.sent(plan, 0.0)
    assert (plan.sends, plan.last_send_s) == (1, 0.0)
    assert book.due(0.3) == []  # within the ack timeout (0.5 s)
    assert book.due(0.6) == [plan]
    book.sent(plan, 0.6)
    assert book.due(1.5) == []  # the second wait is twice the first: 1 s
    assert book.due(1.6) == [plan]
    book.sent(plan, 1.6)
    assert plan.sends == 3
    assert book.due(3.5) == []  # the third: 2 s
    assert book.unacknowledged_dropped == 0
    assert book.due(3.6) == []  # max_sends reached: given up, counted once
    assert book.unacknowledged_dropped == 1
    assert plan.ack is Ack.REJECTED_STALE
    assert book.due(10.0) == []
    assert book.unacknowledged_dropped == 1


def test_the_wait_doubles_up_to_its_ceiling() -> None:
    cfg = DeliveryConfig(ack_timeout_s=0.5, ack_timeout_max_s=4.0, max_sends=5)
    assert [cfg.ack_wait_s(k) for k in range(1, 7)] == [0.5, 1.0, 2.0, 4.0, 4.0, 4.0]
    assert sum(cfg.ack_wait_s(k) for k in range(1, 6)) == 11.5  # given up past Zenoh's 10 s lease


def test_acknowledged_and_request_reply_plans_are_never_due(book: PlanBook) -> None:
    reply = book.issue("v1", ROUTE, 0.0, pushed=False, wall_ns=WALL_NS)
    pushed = book.issue("v2", ROUTE, 0.0, pushed=True, wall_ns=WALL_NS)
    book.sent(pushed, 0.0)
    assert book.on_ack("v2", pushed.plan_id, pushed.version, Ack.ACCEPTED)
    for t in (0.0, 1.0, 100.0):
        assert book.due(t) == []
    assert reply.sends == 0
    assert book.unacknowledged_dropped == 0


def test_a_new_plan_replaces_the_pending_one(book: PlanBook) -> None:
    old = book.issue("v1", ROUTE, 0.0, pushed=True, wall_ns=WALL_NS)
    book.sent(old, 0.0)
    new = book.issue("v1", ROUTE, 0.1, pushed=True, wall_ns=WALL_NS)
    assert book.due(0.2) == [new]


@pytest.mark.parametrize(
    ("current", "received", "decision"),
    [
        ((3, "p3"), ("p3", 3), Ack.DUPLICATE),
        ((3, "p3"), ("p2", 2), Ack.REJECTED_STALE),
        ((3, "p3"), ("px", 3), Ack.REJECTED_STALE),  # same version, other plan: not newer
        ((3, "p3"), ("p3", 1), Ack.REJECTED_STALE),
        ((3, "p3"), ("p4", 4), None),
        ((3, "p3"), ("p9", 9), None),
        ((0, ""), ("p1", 1), None),  # first plan
    ],
)
def test_vehicle_decision(current: tuple[int, str], received: tuple[str, int], decision: Ack | None) -> None:
    assert vehicle_decision(*current, *received) is decision

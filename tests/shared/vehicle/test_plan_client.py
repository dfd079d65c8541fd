"""A vehicle's reply handling (shared/vehicle/plan_client.py `ReplyHandler`): the first valid reply
wins, refusals are counted, each request ends in exactly one outcome when nothing valid came."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from rmmdet.v1.common_pb2 import ErrorCode, ErrorResponse, Header
from rmmdet.v1.planning_pb2 import RoutePlan, RouteResponse

from shared.bus.codec import Counters, MessageDecoder, encode
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.security.plan_signing import PlanSigner, PlanVerifier
from shared.vehicle.plan_client import Outcome, PlanCheck, PlanExpiry, ReplyHandler
from tests.helpers import FakeZBytes

GENUINE = PlanSigner(Ed25519PrivateKey.generate())
ROGUE = PlanSigner(Ed25519PrivateKey.generate())


@dataclass
class Sample:
    payload: FakeZBytes
    encoding: str
    attachment: FakeZBytes | None


@dataclass
class Reply:
    ok: Sample | None = None
    err: Sample | None = None


def plan_reply(signer: PlanSigner, plan_id: str = "a" * 32) -> Reply:
    plan = RoutePlan(vehicle_id="v1", plan_id=plan_id, version=1, lane_ids=["l0"])
    plan.valid_until.FromNanoseconds(2**62)  # checked against max_ttl below: use a huge bound
    header = Header(source_id="cloud/coordinator", seq=1)
    header.stamp.FromNanoseconds(1)
    encoded = encode(RouteResponse(plan=signer.sign(plan)), header)
    attachment = FakeZBytes(encoded.attachment) if encoded.attachment is not None else None
    return Reply(ok=Sample(FakeZBytes(encoded.payload), str(encoded.encoding), attachment))


def error_reply() -> Reply:
    encoded = encode(ErrorResponse(code=ErrorCode.ERROR_CODE_INTERNAL, message="x"))
    return Reply(err=Sample(FakeZBytes(encoded.payload), str(encoded.encoding), None))


@pytest.fixture
def handler() -> tuple[ReplyHandler, BoundedQueue[Outcome], Counters]:
    counters = Counters()
    check = PlanCheck(PlanVerifier([GENUINE._key.public_key()]), max_ttl_s=1e12, counters=counters)
    outcomes: BoundedQueue[Outcome] = BoundedQueue(16, OverflowPolicy.DROP_OLDEST)
    return ReplyHandler("v1", MessageDecoder(RouteResponse, counters), outcomes, check), outcomes, counters


def test_a_forged_reply_first_does_not_hide_the_genuine_one(handler) -> None:
    h, outcomes, counters = handler
    h.on_reply(plan_reply(ROGUE, "b" * 32))  # type: ignore[arg-type]
    h.on_reply(plan_reply(GENUINE))  # type: ignore[arg-type]
    h.on_reply(plan_reply(GENUINE, "c" * 32))  # type: ignore[arg-type]  # after the first valid: not applied
    h.on_done()
    got = outcomes.drain()
    assert [(o.plan.plan_id if o.plan else None, o.error) for o in got] == [("a" * 32, "")]
    assert counters.get("rejected/plan_unknown_key") == 1


def test_a_forged_reply_after_the_answer_is_still_refused_and_counted(handler) -> None:
    """A rogue queryable slower than the coordinator shows in the counters too; an error or a valid
    extra reply after the answer changes nothing but a count."""
    h, outcomes, counters = handler
    h.on_reply(plan_reply(GENUINE))  # type: ignore[arg-type]
    h.on_reply(plan_reply(ROGUE, "b" * 32))  # type: ignore[arg-type]
    h.on_reply(error_reply())  # type: ignore[arg-type]
    h.on_reply(plan_reply(GENUINE, "c" * 32))  # type: ignore[arg-type]
    h.on_done()
    assert [(o.plan.plan_id if o.plan else None, o.error) for o in outcomes.drain()] == [("a" * 32, "")]
    assert counters.get("rejected/plan_unknown_key") == 1 and counters.get("plans/extra_replies") == 1


def test_an_error_reply_is_reported_once_not_again_as_no_reply(handler) -> None:
    h, outcomes, _ = handler
    h.on_reply(error_reply())  # type: ignore[arg-type]
    h.on_reply(error_reply())  # type: ignore[arg-type]
    h.on_done()
    assert [o.error for o in outcomes.drain()] == ["error_internal"]


def test_zenohs_own_timeout_error_is_no_reply_and_asked_again(handler) -> None:
    """A query that got no reply in time ends with Zenoh's error reply `b"Timeout"` (encoding
    zenoh/string), not the coordinator's ErrorResponse: no answer, reported as no_reply (retried), not
    as a coordinator error (error_unspecified, which no vehicle asked again)."""
    h, outcomes, counters = handler
    h.on_reply(Reply(err=Sample(FakeZBytes(b"Timeout"), "zenoh/string", None)))  # type: ignore[arg-type]
    h.on_done()
    assert [o.error for o in outcomes.drain()] == ["no_reply"]
    assert counters.get("plans/transport_errors") == 1


def test_nothing_valid_is_no_reply(handler) -> None:
    h, outcomes, _ = handler
    h.on_reply(plan_reply(ROGUE))  # type: ignore[arg-type]
    h.on_done()
    assert [o.error for o in outcomes.drain()] == ["no_reply"]


def test_plans_expire_at_their_ttl_once() -> None:
    expiry = PlanExpiry()
    expiry.followed("v1", 1_000)
    expiry.followed("v2", 2_000)
    expiry.followed("v1", 3_000)  # a newer plan replaces the older's deadline
    assert expiry.expired(1_500) == []
    assert expiry.expired(2_000) == ["v2"]
    assert expiry.expired(2_500) == []  # reported once
    assert expiry.expired(10_000) == ["v1"]


def test_an_unanswered_request_is_asked_again_with_backoff_until_answered() -> None:
    """Issue 34: across a router restart a vehicle's request sometimes went unanswered for good."""
    from shared.vehicle.plan_client import RequestRetry

    retry = RequestRetry(first_s=1.0, attempts=3)
    assert retry.unanswered("v01", now_s=10.0)
    assert retry.due(10.9) == [] and retry.due(11.0) == ["v01"] and retry.due(11.5) == []
    assert retry.unanswered("v01", now_s=11.2)  # the retry went unanswered too: 2 s later
    assert retry.due(13.1) == [] and retry.due(13.2) == ["v01"]
    retry.answered("v01")  # the next one is answered: the count starts afresh
    assert retry.unanswered("v01", now_s=20.0) and retry.due(21.0) == ["v01"]
    assert retry.unanswered("v01", now_s=21.5) and retry.unanswered("v01", now_s=24.0)
    assert not retry.unanswered("v01", now_s=30.0)  # a fourth in a row: given up (counted)
    assert retry.due(100.0) == []


def test_a_flapping_coordinator_token_asks_every_vehicle_once_per_interval() -> None:
    """A join after a quiet interval: every vehicle asks at once; joins repeated within it (a forged
    token declared and dropped three times, a bouncing link) make one more round at the interval's end."""
    from shared.vehicle.plan_client import JoinAsks

    asks = JoinAsks(min_interval_s=1.0)
    assert not asks.due(0.0)  # nobody joined
    asks.joined()
    assert asks.due(10.0) and not asks.due(10.0)
    for t in (10.2, 10.4, 10.6):
        asks.joined()
        assert not asks.due(t)
    assert not asks.due(10.99)
    assert asks.due(11.0) and not asks.due(11.5)
    asks.joined()
    assert not asks.due(11.9) and asks.due(12.0)


def test_a_flood_of_forged_pushes_does_not_evict_a_genuine_one() -> None:
    """Issue 52 item 9: pushes were queued unchecked (64 places, oldest dropped) and checked only when
    the main loop took them: 64 forged pushes after a genuine one evicted it. Checked on arrival, the
    forged ones never take a place."""
    from shared.bus.node import Received
    from shared.vehicle.plan_client import CheckedPushes

    counters = Counters()
    check = PlanCheck(PlanVerifier([GENUINE._key.public_key()]), max_ttl_s=1e12, counters=counters)
    pushed = CheckedPushes("v1", check, 64, counters)

    def push(signer: PlanSigner, plan_id: str, vehicle: str = "v1") -> None:
        plan = RoutePlan(vehicle_id=vehicle, plan_id=plan_id, version=1, lane_ids=["l0"])
        plan.valid_until.FromNanoseconds(2**62)
        pushed.put(Received("k", signer.sign(plan), Header(), 0, 0))

    answer = RoutePlan(vehicle_id="v1", plan_id="0" * 32, version=1, lane_ids=["l0"])
    check.answered(GENUINE.sign(answer))  # the coordinator answered v1 (it holds v1)
    push(GENUINE, "a" * 32)
    for k in range(1000):
        push(ROGUE, f"{k:032x}")
    push(GENUINE, "b" * 32, vehicle="v2")  # genuine, but another vehicle's
    assert [r.message.plan_id for r in pushed.drain()] == ["a" * 32]
    assert (
        counters.get("rejected/plan_unknown_key") == 1000 and counters.get("rejected/plan_key_mismatch") == 1
    )
    assert counters.get("dropped/pushed") == 0


def test_a_push_is_taken_only_from_the_shard_that_answered_the_vehicle() -> None:
    """Issue 52 item 2: every shard signed with one key, so any shard's host could push a plan to any
    vehicle. With a key per shard, a vehicle takes pushes only from the signer of the last answer to its
    own request (the shard holding it); before any answer, none."""
    from shared.bus.node import Received
    from shared.vehicle.plan_client import CheckedPushes

    shard0, shard1 = PlanSigner(Ed25519PrivateKey.generate()), PlanSigner(Ed25519PrivateKey.generate())
    verifier = PlanVerifier(
        [shard0._key.public_key(), shard1._key.public_key()],
        signers=["plan-signing.region0", "plan-signing.region1"],
    )
    counters = Counters()
    check = PlanCheck(verifier, max_ttl_s=1e12, counters=counters)
    pushed = CheckedPushes("v1", check, 64, counters)

    def plan(signer: PlanSigner, plan_id: str) -> RoutePlan:
        p = RoutePlan(vehicle_id="v1", plan_id=plan_id, version=1, lane_ids=["l0"])
        p.valid_until.FromNanoseconds(2**62)
        return signer.sign(p)

    def push(signer: PlanSigner, plan_id: str) -> bool:
        return pushed.put(Received("k", plan(signer, plan_id), Header(), 0, 0))

    assert not push(shard0, "1" * 32)  # nobody answered v1 yet
    check.answered(plan(shard0, "2" * 32))
    assert push(shard0, "3" * 32) and not push(shard1, "4" * 32)  # shard 1 does not hold v1
    check.answered(plan(shard1, "5" * 32))  # v1 crossed into region 1, which answered it
    assert push(shard1, "6" * 32) and not push(shard0, "7" * 32)
    assert counters.get("rejected/push_not_holder") == 3

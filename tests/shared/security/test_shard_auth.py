"""Shards sign what they tell each other (issue 52 items 1-3): cliques, release requests, handovers."""

from __future__ import annotations

from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from rmmdet.v1.planning_pb2 import PlanHandover, ReleaseRequest
from rmmdet.v1.traffic_pb2 import RegionClique

from shared.security.pki import PLAN_KEY_NAME, shard_plan_key_name
from shared.security.plan_signing import PlanSigner, PlanVerifier
from shared.security.shard_auth import ShardAuth
from shared.timebase import NS_PER_S

KEYS = [Ed25519PrivateKey.generate() for _ in range(3)]  # shard 0, shard 1, the unsharded coordinator
NAMES = [shard_plan_key_name(0), shard_plan_key_name(1), PLAN_KEY_NAME]
VERIFIER = PlanVerifier([k.public_key() for k in KEYS], signers=NAMES)
NOW_NS = 1_000 * NS_PER_S


def auth(index: int) -> ShardAuth:
    return ShardAuth(index, PlanSigner(KEYS[index]), VERIFIER, max_skew_s=0.5)


def test_a_clique_is_taken_only_from_its_regions_shard_with_the_stamp_it_was_signed_with() -> None:
    shard0, shard1, coordinator = auth(0), PlanSigner(KEYS[1]), PlanSigner(KEYS[2])
    clique = shard1.sign(RegionClique(region=1, time_s=[3.0]), NOW_NS)
    assert shard0.problem(clique, NOW_NS, region=1) is None
    assert shard0.problem(clique, NOW_NS + 1, region=1) == "bad_signature"  # replayed under a new stamp
    assert shard0.problem(clique, NOW_NS, region=2) == "wrong_shard"  # shard 1 speaking for region 2
    assert shard0.problem(coordinator.sign(RegionClique(region=1), NOW_NS), NOW_NS, 1) == "wrong_shard"
    tampered = RegionClique()
    tampered.CopyFrom(clique)
    tampered.time_s[0] = 1e6  # a jam drawn elsewhere
    assert shard0.problem(tampered, NOW_NS, region=1) == "bad_signature"
    assert shard0.problem(RegionClique(region=1), NOW_NS, region=1) == "unsigned"
    rogue = PlanSigner(Ed25519PrivateKey.generate()).sign(RegionClique(region=1), NOW_NS)
    assert shard0.problem(rogue, NOW_NS, region=1) == "unknown_key"


def test_a_release_request_is_its_claimed_regions_and_fresh() -> None:
    """Issue 52 item 1: the region a release claims was not authenticated, so a forger made a shard
    release a vehicle 'to region 1'. Now it must be signed by region 1's shard, and recent."""
    shard0, shard1 = auth(0), PlanSigner(KEYS[1])
    ask = shard1.sign(ReleaseRequest(vehicle_id="v1", lane_id="l9", region=1), NOW_NS)
    assert shard0.request_problem(ask, NOW_NS, 1, NOW_NS + NS_PER_S // 10) is None
    assert shard0.request_problem(ask, NOW_NS, 1, NOW_NS + NS_PER_S) == "stale"  # a replay, 1 s on
    claims_other = shard1.sign(ReleaseRequest(vehicle_id="v1", lane_id="l9", region=2), NOW_NS)
    assert shard0.request_problem(claims_other, NOW_NS, 2, NOW_NS) == "wrong_shard"


def test_a_handover_answers_one_request_from_another_shard() -> None:
    shard0, shard1 = auth(0), PlanSigner(KEYS[1])
    reply = shard1.sign(PlanHandover(held=True, version_counter=7), NOW_NS)
    assert shard0.problem(reply, NOW_NS, None) is None
    assert shard0.problem(reply, NOW_NS + 5, None) == "bad_signature"  # an answer to another request
    own = PlanSigner(KEYS[0]).sign(PlanHandover(held=True), NOW_NS)
    assert shard0.problem(own, NOW_NS, None) == "wrong_shard"  # its own key: not another shard's
    unsharded = PlanSigner(KEYS[2]).sign(PlanHandover(held=True), NOW_NS)
    assert shard0.problem(unsharded, NOW_NS, None) == "wrong_shard"

"""Plan signatures: what is signed, what a vehicle refuses, and key loading errors."""

from __future__ import annotations

from pathlib import Path

import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from rmmdet.v1.planning_pb2 import RoutePlan

from shared.bus.streams import limits
from shared.config import ConfigError
from shared.security.pki import create_plan_key
from shared.security.plan_signing import (
    SIGNATURE_BYTES,
    PlanSigner,
    PlanVerifier,
    load_private_key,
    load_public_key,
)
from shared.traffic.plans import plan_problem, version_of

NOW_NS = 1_700_000_000 * 10**9
PLAN_ID = "0123456789abcdef0123456789abcdef"


def plan(**fields: object) -> RoutePlan:
    p = RoutePlan(vehicle_id="v1", plan_id=PLAN_ID, version=3, lane_ids=["a", "b"], **fields)  # type: ignore[arg-type]
    p.valid_until.FromNanoseconds(NOW_NS + 30 * 10**9)
    return p


@pytest.fixture
def signer() -> PlanSigner:
    return PlanSigner(Ed25519PrivateKey.generate())


def verifier_for(*signers: PlanSigner) -> PlanVerifier:
    return PlanVerifier([s._key.public_key() for s in signers])


def test_a_signed_plan_verifies_and_the_header_is_not_covered(signer: PlanSigner) -> None:
    p = signer.sign(plan())
    assert len(p.signature) == SIGNATURE_BYTES and len(p.key_id) == 16
    p.header.stamp.FromNanoseconds(NOW_NS)  # the transport stamps headers after signing
    assert verifier_for(signer).problem(p) is None


@pytest.mark.parametrize(
    ("field", "value"),
    [("vehicle_id", "v2"), ("version", 4), ("plan_id", "f" * 32), ("lane_ids", ["a", "c"])],
)
def test_any_change_to_what_a_vehicle_acts_on_breaks_the_signature(
    signer: PlanSigner, field: str, value: object
) -> None:
    p = signer.sign(plan())
    if field == "lane_ids":
        del p.lane_ids[:]
        p.lane_ids.extend(value)  # type: ignore[arg-type]
    else:
        setattr(p, field, value)
    assert verifier_for(signer).problem(p) == "bad_signature"


def test_unsigned_and_unknown_keys_are_named(signer: PlanSigner) -> None:
    other = PlanSigner(Ed25519PrivateKey.generate())
    assert verifier_for(signer).problem(plan()) == "unsigned"
    assert verifier_for(signer).problem(other.sign(plan())) == "unknown_key"
    assert verifier_for(signer, other).problem(other.sign(plan())) is None  # key rotation: trust both


def test_plan_problem_checks_signature_id_and_ttl(signer: PlanSigner) -> None:
    v = verifier_for(signer)
    assert plan_problem(signer.sign(plan()), v, NOW_NS, 600.0) is None
    assert plan_problem(plan(), v, NOW_NS, 600.0) == "plan_unsigned"
    bad_id = plan()
    bad_id.plan_id = "../../etc"
    assert plan_problem(signer.sign(bad_id), v, NOW_NS, 600.0) == "plan_id"
    huge = plan()
    huge.version = 2**53
    assert plan_problem(signer.sign(huge), v, NOW_NS, 600.0) == "plan_version"
    far = plan()
    far.valid_until.FromNanoseconds(NOW_NS + 601 * 10**9)  # the attack: valid until 2100
    assert plan_problem(signer.sign(far), v, NOW_NS, 600.0) == "plan_ttl"
    no_ttl = plan()
    no_ttl.ClearField("valid_until")
    assert plan_problem(signer.sign(no_ttl), v, NOW_NS, 600.0) == "plan_ttl"


def test_a_plan_issued_before_the_vehicles_run_started_is_a_replay(signer: PlanSigner) -> None:
    """A plan's version is its issue time (µs): one issued before the run started, less the clock skew
    allowed between hosts, is from an earlier run, however long its TTL still runs."""
    v = verifier_for(signer)
    skew_ns = round(limits().max_clock_skew_s * 10**9)
    run_start_ns = NOW_NS - 10 * 10**9
    old, fresh = plan(), plan()
    old.version = version_of(run_start_ns - skew_ns) - 1  # 10.5 s ago: its TTL (30 s) still runs
    fresh.version = version_of(run_start_ns - skew_ns)  # issued on a clock 0.5 s behind, at the start
    assert plan_problem(signer.sign(old), v, NOW_NS, 600.0, run_start_ns) == "plan_before_run"
    assert plan_problem(signer.sign(fresh), v, NOW_NS, 600.0, run_start_ns) is None


def test_a_plan_issued_ahead_of_the_vehicles_clock_is_refused(signer: PlanSigner) -> None:
    """The version is the issue time (µs) and later plans must exceed it: one issued further ahead than
    the clock skew allowed would make every plan after it stale, so it is refused at the edge of the skew."""
    v = verifier_for(signer)
    skew_ns = round(limits().max_clock_skew_s * 10**9)
    ahead, edge = plan(), plan()
    ahead.version = version_of(NOW_NS + skew_ns) + 1
    edge.version = version_of(NOW_NS + skew_ns)  # a coordinator whose clock runs the whole skew ahead
    assert plan_problem(signer.sign(ahead), v, NOW_NS, 600.0) == "plan_future"
    assert plan_problem(signer.sign(edge), v, NOW_NS, 600.0) is None


def test_keys_load_from_files_and_bad_files_are_config_errors(tmp_path: Path) -> None:
    paths = create_plan_key(tmp_path)
    assert (paths.key.stat().st_mode & 0o777) == 0o600
    signer = PlanSigner(load_private_key(paths.key))
    assert PlanVerifier([load_public_key(paths.cert)]).problem(signer.sign(plan())) is None
    with pytest.raises(ConfigError, match="rmmdet pki init"):
        load_private_key(tmp_path / "missing.key")
    garbage = tmp_path / "garbage.pub"
    garbage.write_text("not a key")
    with pytest.raises(ConfigError, match="not a PEM"):
        load_public_key(garbage)
    with pytest.raises(ConfigError, match="must be Ed25519"):
        load_private_key(_ec_key(tmp_path))


def _ec_key(tmp_path: Path) -> Path:
    from shared.security.pki import init_pki

    init_pki(tmp_path / "pki", [])
    return tmp_path / "pki" / "ca.key"


def test_a_vehicle_accepts_the_ttl_the_coordinator_issues_and_no_more(signer: PlanSigner) -> None:
    """Issue 34, item 7: vehicles accepted 600 s while the coordinator issued 120 s. The sim's default
    limit is the coordinator's TTL plus the bus's clock skew."""
    from shared.bus.streams import limits
    from shared.traffic.config import PlannerConfig
    from sim.config import load_sim_settings

    max_ttl_s = load_sim_settings().plan_max_ttl_s
    issued_s = PlannerConfig().plan_ttl_s
    assert max_ttl_s == issued_s + limits().max_clock_skew_s
    v = verifier_for(signer)
    ok = plan()
    ok.valid_until.FromNanoseconds(NOW_NS + round(issued_s * 10**9))
    assert plan_problem(signer.sign(ok), v, NOW_NS, max_ttl_s) is None
    long = plan()
    long.valid_until.FromNanoseconds(NOW_NS + round((issued_s + 1) * 10**9))
    assert plan_problem(signer.sign(long), v, NOW_NS, max_ttl_s) == "plan_ttl"

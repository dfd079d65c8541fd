"""The local CA: chains verify, names and usages are what Zenoh's TLS needs, init is idempotent."""

from __future__ import annotations

import ipaddress
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.x509.oid import ExtendedKeyUsageOID
from rmmdet.v1.planning_pb2 import RoutePlan

from shared.config import ConfigError
from shared.security.identities import router_loopback
from shared.security.pki import (
    NEXT_PLAN_KEY_NAME,
    common_name,
    current_common_names,
    identity_paths,
    init_pki,
    plan_key_paths,
    revoke,
    rotate_ca,
    rotate_plan_key,
    trusted_plan_keys,
)
from shared.security.plan_signing import PlanSigner, PlanVerifier, load_private_key
from shared.traffic.plans import plan_problem


def load(path: Path) -> x509.Certificate:
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_init_makes_a_ca_leaves_and_the_plan_key(tmp_path: Path) -> None:
    report = init_pki(
        tmp_path, ["mec-agent1", "router-cloud"], {"router-cloud": ("10.0.0.1", "cloud.example")}
    )
    assert report.created == ["ca", "plan-signing", "mec-agent1", "router-cloud"]
    ca = load(tmp_path / "ca.pem")
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    leaf = load(identity_paths(tmp_path, "router-cloud").cert)
    leaf.verify_directly_issued_by(ca)
    assert common_name(identity_paths(tmp_path, "router-cloud").cert) == "router-cloud"
    san = leaf.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert set(san.get_values_for_type(x509.DNSName)) == {"router-cloud", "cloud.example"}
    assert set(san.get_values_for_type(x509.IPAddress)) == {
        ipaddress.ip_address(router_loopback("router-cloud")),
        ipaddress.ip_address("10.0.0.1"),
    }
    usages = leaf.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert {ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH} <= set(usages)
    assert not leaf.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for path in (
        tmp_path / "ca.key",
        identity_paths(tmp_path, "mec-agent1").key,
        plan_key_paths(tmp_path).key,
    ):
        assert path.stat().st_mode & 0o777 == 0o600


def test_only_a_router_certificate_may_serve_tls(tmp_path: Path) -> None:
    """Issue 34 item 8: a client identity's leaf names no address and is for client authentication
    only, so its key cannot pose as the router (a TLS client checks serverAuth and the address)."""
    init_pki(tmp_path, ["sensor-agent1-cameras", "router", "router-agent2"])
    for identity, serves in (("sensor-agent1-cameras", False), ("router", True), ("router-agent2", True)):
        leaf = load(identity_paths(tmp_path, identity).cert)
        usages = set(leaf.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value)
        san = leaf.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert (ExtendedKeyUsageOID.SERVER_AUTH in usages) is serves, identity
        assert ExtendedKeyUsageOID.CLIENT_AUTH in usages
        assert bool(san.get_values_for_type(x509.IPAddress)) is serves, identity
    with pytest.raises(ConfigError, match="only a router"):
        init_pki(tmp_path, ["coordinator"], {"coordinator": ("10.0.0.5",)})


def test_init_keeps_what_exists_and_renews_only_leaves(tmp_path: Path) -> None:
    init_pki(tmp_path, ["coordinator"])
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    report = init_pki(tmp_path, ["coordinator", "recorder"])
    assert report.created == ["recorder"] and set(report.kept) == {"ca", "plan-signing", "coordinator"}
    assert all((tmp_path / name).read_bytes() == data for name, data in before.items())
    init_pki(tmp_path, ["coordinator"], renew=True)
    assert (tmp_path / "ca.pem").read_bytes() == before["ca.pem"]
    assert (tmp_path / "coordinator.pem").read_bytes() != before["coordinator.pem"]


def test_a_renewed_key_is_private_whatever_mode_it_had_and_a_symlink_is_refused(tmp_path: Path) -> None:
    """Issue 52 item 9: a key file renewed in place kept a wider mode it had (the creation mode applies
    to new files only), and a symbolic link at a key's path was followed to wherever it pointed."""
    import os
    import stat

    init_pki(tmp_path, ["coordinator"])
    key = tmp_path / "coordinator.key"
    key.chmod(0o644)
    init_pki(tmp_path, ["coordinator"], renew=True)
    assert stat.S_IMODE(key.stat().st_mode) == 0o600
    victim = tmp_path / "victim"
    victim.write_text("mine")
    key.unlink()
    os.symlink(victim, key)
    with pytest.raises(ConfigError, match="symbolic link"):
        init_pki(tmp_path, ["coordinator"], renew=True)
    assert victim.read_text() == "mine"


@pytest.mark.parametrize("name", ["", "ca", "plan-signing", "../etc", "Upper", "a" * 64])
def test_bad_identity_names_are_refused(tmp_path: Path, name: str) -> None:
    with pytest.raises(ConfigError):
        init_pki(tmp_path, [name])
    assert not (tmp_path / "ca.pem").exists()  # refused before anything is written


def test_a_ca_rotation_reissues_every_leaf_and_the_old_ones_no_longer_chain(tmp_path: Path) -> None:
    init_pki(tmp_path, ["operator", "router-cloud"], {"router-cloud": ("10.0.0.1",)})
    old_leaf = load(identity_paths(tmp_path, "operator").cert)
    assert rotate_ca(tmp_path, {"router-cloud": ("10.0.0.1",)}) == ["operator", "router-cloud"]
    ca = load(tmp_path / "ca.pem")
    for identity in ("operator", "router-cloud"):
        load(identity_paths(tmp_path, identity).cert).verify_directly_issued_by(ca)
    with pytest.raises((ValueError, InvalidSignature)):
        old_leaf.verify_directly_issued_by(ca)
    retired = list((tmp_path / "retired").glob("*/ca.pem"))
    assert len(retired) == 1 and not list((tmp_path / "retired").glob("*/*.key"))  # its key is gone
    san = load(identity_paths(tmp_path, "router-cloud").cert).extensions
    assert ipaddress.ip_address("10.0.0.1") in san.get_extension_for_class(
        x509.SubjectAlternativeName
    ).value.get_values_for_type(x509.IPAddress)


def test_a_plan_key_rotation_trusts_current_and_next_then_refuses_the_retired(tmp_path: Path) -> None:
    """Issue 34 item 3: stage -> vehicles trust the current and the next key (plans of either verify);
    promote -> the next is the current, and a plan signed by the retired key is refused."""
    init_pki(tmp_path, ["coordinator"])
    plan = RoutePlan(vehicle_id="v1", plan_id="0" * 32, version=1, lane_ids=["a"])
    plan.valid_until.FromNanoseconds(10**18 + 10**10)
    before = PlanSigner(load_private_key(plan_key_paths(tmp_path).key))
    assert trusted_plan_keys(tmp_path) == [plan_key_paths(tmp_path).cert]
    assert rotate_plan_key(tmp_path) == "staged"
    nxt = PlanSigner(load_private_key(plan_key_paths(tmp_path, NEXT_PLAN_KEY_NAME).key))
    during = PlanVerifier.load(trusted_plan_keys(tmp_path))
    assert during.problem(before.sign(plan)) is None and during.problem(nxt.sign(plan)) is None
    assert rotate_plan_key(tmp_path) == "promoted"
    after = PlanVerifier.load(trusted_plan_keys(tmp_path))
    assert trusted_plan_keys(tmp_path) == [plan_key_paths(tmp_path).cert]
    assert after.problem(nxt.sign(plan)) is None
    assert plan_problem(before.sign(plan), after, 10**18, 600.0) == "plan_unknown_key"
    assert not plan_key_paths(tmp_path, NEXT_PLAN_KEY_NAME).key.exists()
    assert len(list((tmp_path / "retired").glob("*/plan-signing.pub"))) == 1


def test_a_watching_verifier_follows_a_rotation_without_a_restart(tmp_path: Path) -> None:
    """Issue 52 item 9: a vehicle read its trusted plan keys once, so a retired key stayed trusted (and a
    staged one untrusted) until it restarted."""
    init_pki(tmp_path, ["coordinator"])
    plan = RoutePlan(vehicle_id="v1", plan_id="0" * 32, version=1, lane_ids=["a"])
    plan.valid_until.FromNanoseconds(10**18 + 10**10)
    before = PlanSigner(load_private_key(plan_key_paths(tmp_path).key))
    vehicle = PlanVerifier.watching(lambda: trusted_plan_keys(tmp_path), recheck_s=0.0)
    assert vehicle.problem(before.sign(plan)) is None
    assert rotate_plan_key(tmp_path) == "staged"
    nxt = PlanSigner(load_private_key(plan_key_paths(tmp_path, NEXT_PLAN_KEY_NAME).key))
    assert vehicle.problem(nxt.sign(plan)) is None  # the staged key: trusted at once
    assert rotate_plan_key(tmp_path) == "promoted"
    assert vehicle.problem(nxt.sign(plan)) is None
    assert vehicle.problem(before.sign(plan)) == "unknown_key"  # the retired key: no longer trusted


def test_one_leaf_is_revoked_alone_under_a_new_common_name(tmp_path: Path) -> None:
    """Issue 52 item 9: one leaf could not be revoked without rotating the CA (every host reissued).
    `revoke` reissues only that leaf, under `<identity>.<generation>`, keeping a router's extra names."""
    init_pki(tmp_path, ["operator", "router-cloud", "mec-agent1"], {"router-cloud": ("10.0.0.1",)})
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    old = load(identity_paths(tmp_path, "router-cloud").cert)
    assert revoke(tmp_path, "router-cloud") == "router-cloud.1"
    changed = {p.name for p in tmp_path.iterdir() if p.is_file() and before.get(p.name) != p.read_bytes()}
    assert changed == {"router-cloud.pem", "router-cloud.key", "generations.json"}
    new = load(identity_paths(tmp_path, "router-cloud").cert)
    new.verify_directly_issued_by(load(tmp_path / "ca.pem"))
    assert common_name(identity_paths(tmp_path, "router-cloud").cert) == "router-cloud.1"
    names = x509.SubjectAlternativeName
    assert set(new.extensions.get_extension_for_class(names).value) == set(
        old.extensions.get_extension_for_class(names).value
    )
    assert revoke(tmp_path, "router-cloud") == "router-cloud.2"
    assert current_common_names(tmp_path) == {"router-cloud": "router-cloud.2"}
    init_pki(tmp_path, ["router-cloud"], renew=True)  # a renewal keeps the generation
    assert common_name(identity_paths(tmp_path, "router-cloud").cert) == "router-cloud.2"
    with pytest.raises(ConfigError, match="no certificate"):
        revoke(tmp_path, "recorder")
    (tmp_path / "generations.json").write_text('{"operator": -1}')
    with pytest.raises(ConfigError, match=r"generations\.json"):
        current_common_names(tmp_path)


def test_each_router_names_its_own_loopback_address_only() -> None:
    """Issue 52 item 9: every router's certificate named 127.0.0.1, so one site router's stolen key
    served the clients of any other host's router on that host's loopback while it restarted. Each
    router now listens on, and its certificate names, a loopback address of its own."""
    names = ["router-cloud", "router-agent1", "router-agent2", "router-agent3"]
    addresses = {router_loopback(n) for n in names}
    assert len(addresses) == len(names) and "127.0.0.1" not in addresses
    assert all(ipaddress.ip_address(a) in ipaddress.ip_network("127.0.0.0/8") for a in addresses)
    assert router_loopback("router") == "127.0.0.1"  # the one-host router (`make up`)


def test_a_shards_plan_key_rotates_on_its_own(tmp_path: Path) -> None:
    """`rmmdet pki rotate --plan-key --shard 1`: shard 1's key is staged (trusted beside the current one,
    as the same signer) and promoted; the coordinator's and shard 0's keys are untouched."""
    from shared.security.identities import shard_identity
    from shared.security.pki import shard_plan_key_name, signer_name

    init_pki(tmp_path, [shard_identity(0), shard_identity(1)])
    name = shard_plan_key_name(1)
    others = {p: p.read_bytes() for p in tmp_path.glob("plan-signing*") if name not in p.name}
    assert rotate_plan_key(tmp_path, name) == "staged"
    staged = plan_key_paths(tmp_path, f"{name}.next").cert
    assert staged in trusted_plan_keys(tmp_path) and signer_name(staged) == name
    assert rotate_plan_key(tmp_path, name) == "promoted"
    assert not staged.exists() and plan_key_paths(tmp_path, name).cert in trusted_plan_keys(tmp_path)
    assert all(p.read_bytes() == data for p, data in others.items())

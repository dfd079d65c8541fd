"""Mutual TLS and access control on one host (issue 16): a router-cloud rendered from a layout with a
fresh CA, and sessions holding the identities' certificates.

- a client without a certificate, with one from another CA, or over plain TCP cannot connect;
- each identity can do only what proto/streams.yaml grants its role, with its own bindings: a put
  outside them is not delivered to a subscriber that may read everything (counted at the receiver),
  a rogue queryable on the route RPC key never answers a vehicle, a vehicle cannot ask for another
  vehicle's plans, and an unknown common name can do nothing at all.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from shared.bus.node import Node
from shared.bus.session import SessionUnavailable, open_session
from shared.bus.streams import data_keys, get_stream
from shared.bus.zenoh_config import DEFAULT_CLIENT_CONFIG
from shared.paths import DEFAULT_SCENE
from shared.scene.calibration import calibration_set
from shared.scene.scene import Scene
from shared.security.pki import init_pki, revoke, rotate_ca
from tests.helpers import free_port, spawn, stop, wait_port, wait_until
from tests.integration.secure_sites import Deployment, Inbox, make_deployment

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

#: Time for a denied put to have arrived if it were going to (deliveries on loopback take < 10 ms).
SETTLE_S = 0.5
REFUSED_WITHIN_S = 3.0


def one_host_layout(services: list[str]) -> dict:
    """A layout of the cloud host alone (router-cloud on 127.0.0.1) listing `services` (not run)."""
    return {
        "port": free_port(),
        "hosts": {
            "cloud": {
                "address": "127.0.0.1",
                "router": "router-cloud",
                "services": [{"identity": s, "command": ["-c", "pass"]} for s in services],
            }
        },
    }


@pytest.fixture(scope="module")
def deployment(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Deployment]:
    tmp = tmp_path_factory.mktemp("secure")
    services = [
        "coordinator",
        "recorder",
        "mec-agent1",
        "sensor-agent1-cameras",
        "vehicle-v1",
        "vehicle-v2",
        "sim",
    ]
    layout = one_host_layout(services)
    dep = make_deployment(tmp, layout, extra_identities=("mallory", "router-agent1"))
    config = tmp / "router-cloud.json"
    config.write_text(str(dep.config("router-cloud")))
    router = spawn(["-m", "services.router", "--config", str(config)])
    try:
        wait_port(dep.layout.port)
        yield dep
    finally:
        stop(router)


def tls_client(dep: Deployment, *, cert_dir: Path | None, identity: str = "operator") -> zenoh.Config:
    """A client config like the operator's, with another (or no) client certificate."""
    conf = dep.config("operator")
    tls = json.loads(conf.get_json("transport/link/tls"))
    if cert_dir is None:
        tls["enable_mtls"] = False
        for k in ("connect_certificate", "connect_private_key", "listen_certificate", "listen_private_key"):
            tls[k] = None
    else:
        for side in ("connect", "listen"):
            tls[f"{side}_certificate"] = str(cert_dir / f"{identity}.pem")
            tls[f"{side}_private_key"] = str(cert_dir / f"{identity}.key")
    conf.insert_json5("transport/link/tls", json.dumps(tls))
    return conf


def test_only_clients_with_a_certificate_of_the_deployment_ca_connect(
    deployment: Deployment, tmp_path: Path
) -> None:
    with open_session(deployment.config("operator"), timeout_s=10) as session:
        assert session.info.routers_zid()
    foreign = tmp_path / "foreign"
    init_pki(foreign, ["operator"])  # same name, another CA
    plain_tcp = zenoh.Config.from_file(str(DEFAULT_CLIENT_CONFIG))
    plain_tcp.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{deployment.layout.port}"]))
    for conf in (tls_client(deployment, cert_dir=None), tls_client(deployment, cert_dir=foreign), plain_tcp):
        t0 = time.monotonic()
        with pytest.raises(SessionUnavailable):
            open_session(conf, timeout_s=REFUSED_WITHIN_S)
        assert time.monotonic() - t0 < REFUSED_WITHIN_S + 2


def rogue_router(dep: Deployment, identity: str, address: str, port: int) -> zenoh.Config:
    """A router's config listening on `address:port` with `identity`'s certificate and key: a key holder
    posing as the router (while the real one restarts, its port is free)."""
    conf = dep.config("router-cloud")
    tls = json.loads(conf.get_json("transport/link/tls"))
    tls["listen_certificate"] = str(dep.pki / f"{identity}.pem")
    tls["listen_private_key"] = str(dep.pki / f"{identity}.key")
    conf.insert_json5("transport/link/tls", json.dumps(tls))
    conf.insert_json5("listen/endpoints", json.dumps([f"tls/{address}:{port}"]))
    return conf


def test_only_the_hosts_own_router_certificate_can_serve_its_clients(deployment: Deployment) -> None:
    """Issue 34 item 8: a service's key (here a sensor group's) cannot pose as the router: its
    certificate names no address and is for client authentication only, so the operator's TLS client
    refuses it. Issue 52 item 9: nor can another router's key (a site's), as every router's certificate
    named 127.0.0.1 and clients connected there: now each router has a loopback address of its own. With
    the router's own certificate the same listener is accepted (the control)."""
    endpoint = json.loads(deployment.config("operator").get_json("connect/endpoints"))[0]
    address = endpoint.removeprefix("tls/").rsplit(":", 1)[0]  # where the operator finds its router
    for identity, accepted in (
        ("sensor-agent1-cameras", False),
        ("router-agent1", False),
        ("router-cloud", True),
    ):
        port = free_port()
        with zenoh.open(rogue_router(deployment, identity, address, port)):
            wait_port(port, address)
            client = deployment.config("operator")
            client.insert_json5("connect/endpoints", json.dumps([f"tls/{address}:{port}"]))
            if accepted:
                with open_session(client, timeout_s=10) as session:
                    assert session.info.routers_zid()
            else:
                with pytest.raises(SessionUnavailable):
                    open_session(client, timeout_s=REFUSED_WITHIN_S)


# (identity, key, delivered?) — each put is made by `identity` and watched by the operator.
PUTS = [
    ("mec-agent1", "rmmdet/v1/agent1/objects", True),
    ("mec-agent1", "rmmdet/v1/agent2/objects", False),  # agent1's MEC cannot speak for agent2
    ("mec-agent1", "rmmdet/v1/agent1/sensor/camera/cam_11", False),  # nor for its own sensors
    ("mec-agent1", "rmmdet/v1/cloud/plans/v1", False),
    ("sensor-agent1-cameras", "rmmdet/v1/agent1/sensor/camera/cam_11", True),
    ("sensor-agent1-cameras", "rmmdet/v1/agent1/sensor/lidar/lidar_1", False),  # another kind
    ("sensor-agent1-cameras", "rmmdet/v1/agent2/sensor/camera/cam_21", False),  # another agent
    ("sensor-agent1-cameras", "rmmdet/v1/sim/ground_truth", False),
    ("vehicle-v1", "rmmdet/v1/vehicles/v1/plan_ack", True),
    ("vehicle-v1", "rmmdet/v1/vehicles/v2/plan_ack", False),  # a vehicle acks only its own plans
    ("vehicle-v1", "rmmdet/v1/cloud/plans/v1", False),  # forged plan
    ("coordinator", "rmmdet/v1/cloud/plans/v1", True),  # only the coordinator publishes plans
    ("coordinator", "rmmdet/v1/vehicles/v1/plan_ack", False),  # forged ack
    ("recorder", "rmmdet/v1/agent1/objects", False),  # the recorder reads only
    ("sim", "rmmdet/v1/sim/ground_truth", True),
    ("sim", "rmmdet/v1/vehicles/v1/plan_ack", False),  # the world holds no vehicle's rights (issue 34 4.)
    ("mallory", "rmmdet/v1/agent1/objects", False),  # a certificate of the CA, but no role
]


def test_each_identity_puts_only_on_its_own_keys(deployment: Deployment) -> None:
    inbox = Inbox()
    with deployment.session("operator") as watcher:
        subs = [watcher.declare_subscriber(k, inbox) for k in data_keys()]  # a reader: stream by stream
        sessions = {ident: deployment.session(ident) for ident in {p[0] for p in PUTS}}
        try:
            time.sleep(SETTLE_S)  # subscriptions propagated
            for i, (ident, key, _) in enumerate(PUTS):
                sessions[ident].put(key, f"{i}".encode())
            allowed = [(k, f"{i}".encode()) for i, (_, k, ok) in enumerate(PUTS) if ok]
            wait_until(lambda: all(p in inbox.payloads(k) for k, p in allowed), 5, "authorized puts")
            time.sleep(SETTLE_S)
        finally:
            for sub in subs:
                sub.undeclare()
            for s in sessions.values():
                s.close()
    delivered = {(k, p) for k, p in inbox.samples}
    unauthorized = [
        (ident, key)
        for i, (ident, key, ok) in enumerate(PUTS)
        if not ok and (key, f"{i}".encode()) in delivered
    ]
    assert unauthorized == [], f"unauthorized puts delivered: {unauthorized}"


def test_a_rogue_queryable_never_answers_a_vehicle_and_a_vehicle_asks_only_for_itself(
    deployment: Deployment,
) -> None:
    rpc = get_stream("route_rpc")
    with (
        deployment.session("coordinator") as coordinator,
        deployment.session("mec-agent1") as rogue,
        deployment.session("vehicle-v1") as vehicle,
    ):
        genuine = coordinator.declare_queryable(rpc.pattern(), lambda q: q.reply(q.key_expr, b"genuine"))
        forged = rogue.declare_queryable(rpc.pattern(), lambda q: q.reply(q.key_expr, b"forged"))
        time.sleep(SETTLE_S)
        try:
            own = [r.ok.payload.to_bytes() for r in vehicle.get(rpc.key(vehicle="v1"), timeout=2.0) if r.ok]
            other = [r for r in vehicle.get(rpc.key(vehicle="v2"), timeout=1.0)]
        finally:
            genuine.undeclare()
            forged.undeclare()
    assert own == [b"genuine"]
    assert other == []  # vehicle-v1 may not ask for v2's plans (one plan-book entry per identity)


def test_a_vehicle_is_not_told_of_another_vehicles_plan_subscription(deployment: Deployment) -> None:
    """Issue 52 item 9: every publisher was told of subscriptions on the whole data space (to route its
    puts to the recorder's `rmmdet/v1/**`), so vehicle v1 learned that v2 subscribes to its plans (v2's
    id). Now a vehicle is told only of its own streams' key spaces: a publisher of v1's on v2's plan key
    sees no subscriber, the coordinator's does (the control)."""
    plans_v2 = get_stream("route_plan").key(vehicle="v2")
    with (
        deployment.session("vehicle-v2") as v2,
        deployment.session("vehicle-v1") as v1,
        deployment.session("coordinator") as coordinator,
    ):
        sub = v2.declare_subscriber(plans_v2, lambda _s: None)
        probe = v1.declare_publisher(plans_v2)
        control = coordinator.declare_publisher(plans_v2)
        try:
            wait_until(lambda: control.matching_status.matching, 5, "the coordinator sees v2's subscription")
            time.sleep(SETTLE_S)
            assert not probe.matching_status.matching
        finally:
            for entity in (probe, control, sub):
                entity.undeclare()


def test_the_sim_cannot_ask_for_a_vehicles_plan(deployment: Deployment) -> None:
    """The sim drives its vehicles under their own identities (`--vehicle-configs`); its own identity
    asks for nobody's plan (a stolen sim key forges no vehicle)."""
    rpc = get_stream("route_rpc")
    with deployment.session("coordinator") as coordinator, deployment.session("sim") as sim:
        genuine = coordinator.declare_queryable(rpc.pattern(), lambda q: q.reply(q.key_expr, b"genuine"))
        time.sleep(SETTLE_S)
        try:
            replies = list(sim.get(rpc.key(vehicle="v1"), timeout=1.0))
        finally:
            genuine.undeclare()
    assert [r for r in replies if r.ok is not None] == []


def test_must_deliver_history_works_under_access_control(deployment: Deployment) -> None:
    """The advanced publisher/subscriber's own keys (`<key>/@adv/...`: token, cache queryable, queries)
    are granted with the stream: a MEC joining late gets the sim's cached calibration at once."""
    calibration = calibration_set(Scene.load(DEFAULT_SCENE), "agent1")
    with Node(deployment.config("sim"), service="sim", instance="sim", scope="sim") as sim:
        sim.publisher("calibration", agent="agent1").put(calibration)
        time.sleep(SETTLE_S)  # long published before the MEC comes
        with Node(deployment.config("mec-agent1"), service="mec", instance="agent1", scope="agent1") as mec:
            sub = mec.subscribe_stream("calibration", agent="agent1")
            item = sub.recv(timeout=REFUSED_WITHIN_S)
            assert item is not None, "no calibration from the publisher's cache under access control"
            assert item.message.SerializeToString() == calibration.SerializeToString()


def test_a_node_holds_only_its_own_presence_token_and_health_key(deployment: Deployment) -> None:
    """Issue 34 item 5: the camera group of agent1 may hold its own presence token and answer its own
    health queries, not its sibling lidar group's (the ACL binds the instance chunk to the identity)."""
    alive, health = get_stream("alive"), get_stream("health")
    ids = {"own": "agent1-cameras", "sibling": "agent1-lidars"}
    tokens = {k: alive.key(scope="agent1", service="sensor", instance=i) for k, i in ids.items()}
    healths = {k: health.key(scope="agent1", service="sensor", instance=i) for k, i in ids.items()}
    with deployment.session("operator") as operator, deployment.session("sensor-agent1-cameras") as cams:
        declared = [cams.liveliness().declare_token(key) for key in tokens.values()]
        declared += [
            cams.declare_queryable(k, lambda q: q.reply(q.key_expr, b"ok")) for k in healths.values()
        ]
        time.sleep(SETTLE_S)
        try:
            seen = {
                str(r.ok.key_expr) for r in operator.liveliness().get(alive.pattern(scope="agent1")) if r.ok
            }
            answered = {k: [r for r in operator.get(key, timeout=1.0) if r.ok] for k, key in healths.items()}
        finally:
            for d in declared:
                d.undeclare()
    assert tokens["own"] in seen and tokens["sibling"] not in seen, seen
    assert len(answered["own"]) == 1 and answered["sibling"] == [], answered


def test_after_a_ca_rotation_an_old_certificate_is_refused(tmp_path: Path) -> None:
    """Issue 34 item 3: `rmmdet pki rotate --ca` reissues every leaf under a new CA; a router started
    with the new `ca.pem` accepts the operator's new certificate and refuses its old one (a stolen or
    renewed-away certificate: Zenoh's TLS has no revocation lists, the CA rotation is the revocation)."""
    layout = {"port": free_port(), "hosts": {"cloud": {"address": "127.0.0.1", "router": "router-cloud"}}}
    dep = make_deployment(tmp_path, layout)
    old = tmp_path / "old"
    old.mkdir()
    for suffix in (".pem", ".key"):
        shutil.copy(dep.pki / f"operator{suffix}", old / f"operator{suffix}")
    rotate_ca(dep.pki, dep.layout.certificate_names())
    config = tmp_path / "router-cloud.json"
    config.write_text(str(dep.config("router-cloud")))
    router = spawn(["-m", "services.router", "--config", str(config)])
    try:
        wait_port(dep.layout.port)
        with open_session(dep.config("operator"), timeout_s=10) as session:
            assert session.info.routers_zid()
        with pytest.raises(SessionUnavailable):
            open_session(tls_client(dep, cert_dir=old), timeout_s=REFUSED_WITHIN_S)
    finally:
        stop(router)


def test_one_revoked_leaf_is_refused_and_no_other_is_touched(tmp_path: Path) -> None:
    """Issue 52 item 9 (acceptance): `rmmdet pki revoke vehicle-v1` reissues that leaf alone; a router
    rendered afterwards grants the old certificate nothing (its ack is not delivered, its route request
    unanswered) while the new one and every other identity, its files untouched, work as before."""
    services = ["coordinator", "mec-agent1", "vehicle-v1"]
    layout = one_host_layout(services)
    dep = make_deployment(tmp_path, layout)
    old = tmp_path / "old"
    old.mkdir()
    for suffix in (".pem", ".key"):
        shutil.copy(dep.pki / f"vehicle-v1{suffix}", old / f"vehicle-v1{suffix}")
    others = {p.name: p.read_bytes() for p in dep.pki.glob("*.*") if not p.name.startswith("vehicle-v1")}
    assert revoke(dep.pki, "vehicle-v1") == "vehicle-v1.1"
    assert {p.name: p.read_bytes() for p in dep.pki.glob("*.*") if p.name in others} == others
    config = tmp_path / "router-cloud.json"
    config.write_text(str(dep.config("router-cloud")))
    router = spawn(["-m", "services.router", "--config", str(config)])
    rpc, ack = get_stream("route_rpc"), "rmmdet/v1/vehicles/v1/plan_ack"
    inbox = Inbox()
    try:
        wait_port(dep.layout.port)
        stolen = tls_client(dep, cert_dir=old, identity="vehicle-v1")
        with (
            dep.session("operator") as watcher,
            dep.session("coordinator") as coordinator,
            dep.session("mec-agent1") as mec,
            dep.session("vehicle-v1") as current,
            open_session(stolen, timeout_s=10) as revoked,
        ):
            for k in data_keys():
                watcher.declare_subscriber(k, inbox)
            coordinator.declare_queryable(rpc.pattern(), lambda q: q.reply(q.key_expr, b"plan"))
            time.sleep(SETTLE_S)
            revoked.put(ack, b"revoked")
            current.put(ack, b"current")
            mec.put("rmmdet/v1/agent1/objects", b"other")
            wait_until(lambda: inbox.payloads(ack) == [b"current"], 5, "the current leaf's ack")
            assert [r.ok for r in current.get(rpc.key(vehicle="v1"), timeout=2.0) if r.ok]
            answered = [r for r in revoked.get(rpc.key(vehicle="v1"), timeout=1.0) if r.ok]
            time.sleep(SETTLE_S)
    finally:
        stop(router)
    assert inbox.payloads(ack) == [b"current"] and answered == []
    assert inbox.payloads("rmmdet/v1/agent1/objects") == [b"other"]

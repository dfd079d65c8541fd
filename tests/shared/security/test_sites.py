"""Site layouts rendered into Zenoh configs and supervisord programs."""

from __future__ import annotations

import datetime as dt
import json
import logging
import re
from pathlib import Path

import pytest
import zenoh
from supervisor.datatypes import dict_of_key_value_pairs

from shared.config import ConfigError
from shared.security import pki as pki_module
from shared.security.identities import router_loopback
from shared.security.pki import init_pki
from shared.security.sites import (
    DEFAULT_LAYOUT,
    bundle_host,
    check_certificate,
    identity_config,
    load_layout,
    render_host,
    revocation_steps,
    router_subjects,
    supervisor_program,
)

THREE_SITES = DEFAULT_LAYOUT


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    layout = load_layout(THREE_SITES)
    path = tmp_path_factory.mktemp("pki")
    init_pki(path, layout.all_identities(), layout.certificate_names())
    return path


def config(pki: Path, host: str, identity: str) -> zenoh.Config:
    return zenoh.Config.from_json5(identity_config(load_layout(THREE_SITES), host, identity, pki))


def get(conf: zenoh.Config, key: str):
    return json.loads(conf.get_json(key))


def test_routers_see_each_other_as_their_side_of_the_link() -> None:
    layout = load_layout(THREE_SITES)
    cloud = router_subjects(layout, "cloud")
    assert cloud["router-agent1"] == [
        "router-agent1",
        "sensor-agent1-cameras",
        "sensor-agent1-lidars",
        "mec-agent1",
    ]
    assert cloud["sim"] == ["sim"] and cloud["coordinator"] == ["coordinator"] and "operator" in cloud
    assert cloud["vehicle-v03"] == ["vehicle-v03"]  # each of the sim's vehicles connects as itself
    assert "mec-agent1" not in cloud  # it reaches the cloud only through its site's router
    site = router_subjects(layout, "site1")
    assert set(site) == {"sensor-agent1-cameras", "sensor-agent1-lidars", "mec-agent1", "router-cloud"}
    assert "mec-agent1" not in site["router-cloud"] and "coordinator" in site["router-cloud"]


def test_endpoints_and_tls(pki: Path) -> None:
    mec = config(pki, "site1", "mec-agent1")
    site1 = router_loopback("router-agent1")
    assert get(mec, "connect/endpoints") == [f"tls/{site1}:7447"]  # its site's router, on its own address
    tls = get(mec, "transport/link/tls")
    assert tls["enable_mtls"] and tls["verify_name_on_connect"]
    assert tls["connect_certificate"] == str(pki / "mec-agent1.pem")
    assert get(mec, "access_control/enabled") is False  # clients do not filter; routers do
    site_router = config(pki, "site1", "router-agent1")
    assert get(site_router, "listen/endpoints") == [f"tls/{site1}:7447"]  # no inbound port on a site
    assert get(site_router, "connect/endpoints") == ["tls/10.77.0.10:7447"]
    assert get(site_router, "access_control/default_permission") == "deny"
    cloud = config(pki, "cloud", "router-cloud")
    cloud_loopback = router_loopback("router-cloud")
    assert get(cloud, "listen/endpoints") == ["tls/10.77.0.10:7447", f"tls/{cloud_loopback}:7447"]
    assert get(config(pki, "cloud", "coordinator"), "connect/endpoints") == [f"tls/{cloud_loopback}:7447"]
    assert get(config(pki, "vehicles", "sim"), "connect/endpoints") == ["tls/10.77.0.10:7447"]
    assert get(cloud, "transport/link/tx/lease") == 1000


def bundle(pki: Path, host: str, tmp_path: Path) -> Path:
    bundle_host(load_layout(THREE_SITES), host, pki, tmp_path / f"{host}-pki")
    return tmp_path / f"{host}-pki"


def test_render_host_writes_configs_and_a_supervisord_conf(pki: Path, tmp_path: Path) -> None:
    conf = render_host(load_layout(THREE_SITES), "cloud", bundle(pki, "cloud", tmp_path), tmp_path)
    text = conf.read_text()
    assert "[program:router-cloud]" in text and "[program:coordinator]" in text
    assert (tmp_path / "coordinator.json").exists() and "RMMDET_COORD_PLAN_SIGNING_KEY" in text
    with pytest.raises(ConfigError, match="no host"):
        render_host(load_layout(THREE_SITES), "mars", pki, tmp_path)


def test_a_host_gets_what_it_runs_and_never_the_ca_key(pki: Path, tmp_path: Path) -> None:
    """Issue 34 item 3: the CA key stays where certificates are made. A host's bundle holds the CA
    certificate, its own identities' leaves and keys and the plan-key half it uses; the launcher
    refuses a PKI directory with the CA key in it."""
    layout = load_layout(THREE_SITES)
    site1 = {p.name for p in bundle_host(layout, "site1", pki, tmp_path / "site1")}
    own = {"router-agent1", "sensor-agent1-cameras", "sensor-agent1-lidars", "mec-agent1"}
    assert site1 == {"ca.pem"} | {f"{i}.{ext}" for i in own for ext in ("pem", "key")}
    cloud = {p.name for p in bundle_host(layout, "cloud", pki, tmp_path / "cloud")}
    assert "plan-signing.key" in cloud and "plan-signing.pub" not in cloud
    vehicles = {p.name for p in bundle_host(layout, "vehicles", pki, tmp_path / "vehicles")}
    assert "plan-signing.pub" in vehicles and "plan-signing.key" not in vehicles
    assert "vehicle-v04.key" in vehicles and "vehicle-v04.key" not in site1 | cloud
    for name in ("ca.key", "operator.key"):
        assert name not in site1 | cloud | vehicles
    assert ((tmp_path / "site1" / "mec-agent1.key").stat().st_mode & 0o777) == 0o600
    with pytest.raises(ConfigError, match="CA's private key"):
        render_host(layout, "site1", pki, tmp_path / "out")
    render_host(layout, "site1", tmp_path / "site1", tmp_path / "out")  # the bundle is enough
    with pytest.raises(ConfigError, match="another directory"):
        bundle_host(layout, "site1", pki, pki)


def test_the_vehicles_host_gives_the_sim_each_vehicles_identity(pki: Path, tmp_path: Path) -> None:
    text = render_host(
        load_layout(THREE_SITES), "vehicles", bundle(pki, "vehicles", tmp_path), tmp_path
    ).read_text()
    command = next(ln for ln in text.splitlines() if ln.startswith("command=") and "services.sim" in ln)
    assert f"--vehicle-configs {tmp_path / 'vehicles'}" in command
    configs = sorted(p.name for p in (tmp_path / "vehicles").iterdir())
    assert configs == [f"vehicle-v{i:02d}.json" for i in range(10)]
    conf = zenoh.Config.from_json5((tmp_path / "vehicles" / "vehicle-v04.json").read_text())
    assert get(conf, "transport/link/tls/connect_certificate").endswith("vehicle-v04.pem")
    assert get(conf, "connect/endpoints") == ["tls/10.77.0.10:7447"]


def test_environment_values_survive_supervisord_quoting(tmp_path: Path) -> None:
    env = {"A": json.dumps(["/p/plan-signing.pub"]), "B": "50%"}
    program = supervisor_program("x", ["-c", "pass"], tmp_path / "x.json", env, tmp_path)
    line = next(ln for ln in program.splitlines() if ln.startswith("environment="))
    parsed = dict_of_key_value_pairs(line.removeprefix("environment=").replace("%%", "%"))
    assert parsed == {**env, "PYTHONUNBUFFERED": "1"}


def test_the_cloud_certificate_must_name_its_address(tmp_path: Path) -> None:
    layout = load_layout(THREE_SITES)
    init_pki(tmp_path / "pki", layout.identities("cloud"))  # no --name router-cloud=10.77.0.10
    bundle_host(layout, "cloud", tmp_path / "pki", tmp_path / "cloud")
    with pytest.raises(ConfigError, match=re.escape("pki init --renew --name router-cloud=10.77.0.10")):
        render_host(layout, "cloud", tmp_path / "cloud", tmp_path / "out")


def test_an_expired_certificate_is_refused_and_one_near_expiry_warned(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 34 item 3: leaves live LEAF_VALIDITY_DAYS; the launcher refuses an expired one (its TLS
    links would close) and warns RENEW_WITHIN_DAYS ahead."""
    now = pki_module._now()
    for identity, age_days in (("recorder", pki_module.LEAF_VALIDITY_DAYS + 1), ("operator", 80)):
        monkeypatch.setattr(pki_module, "_now", lambda age=age_days: now - dt.timedelta(days=age))
        init_pki(tmp_path, [identity])
    monkeypatch.setattr(pki_module, "_now", lambda: now)
    with pytest.raises(ConfigError, match="expired"):
        check_certificate(tmp_path, "recorder")
    with caplog.at_level(logging.WARNING, logger="shared.security.sites"):
        check_certificate(tmp_path, "operator")
    assert "expires in 10 days" in caplog.text
    init_pki(tmp_path, ["coordinator"])
    leaf = pki_module.x509.load_pem_x509_certificate((tmp_path / "coordinator.pem").read_bytes())
    assert 89 < pki_module.days_left(leaf) <= pki_module.LEAF_VALIDITY_DAYS == 90


@pytest.mark.parametrize(
    "hosts",
    [
        {"a": {"address": "10.0.0.1", "services": ["coordinator"]}},  # no cloud router
        {
            "a": {"address": "10.0.0.1", "router": "router-cloud", "services": ["coordinator"]},
            "b": {"address": "10.0.0.2", "services": ["coordinator"]},  # one identity on two hosts
        },
        {"a": {"address": "not-an-ip", "router": "router-cloud"}},
        {"a": {"address": "10.0.0.1", "router": "router-cloud", "services": ["mallory"]}},
        {"a": {"address": "10.0.0.1", "router": "mec-agent1"}},  # not a router
        {"a": {"address": "10.0.0.1", "router": "router-cloud", "vehicles": ["v01"]}},  # no sim to drive it
        {"a": {"address": "10.0.0.1", "router": "router-cloud", "services": ["sim"], "vehicles": ["v-1"]}},
        {
            "a": {"address": "10.0.0.1", "router": "router-cloud", "services": ["sim"], "vehicles": ["v1"]},
            "b": {"address": "10.0.0.2", "services": ["vehicle-v1"]},  # the same vehicle twice
        },
    ],
)
def test_bad_layouts_are_config_errors(tmp_path: Path, hosts: dict) -> None:
    path = tmp_path / "layout.yaml"
    path.write_text(json.dumps({"hosts": hosts}))
    with pytest.raises(ConfigError):
        load_layout(path)


def test_a_revoked_leaf_is_granted_nothing_and_its_holder_must_take_the_new_bundle(tmp_path: Path) -> None:
    """Issue 52 item 9: after `pki.revoke`, every router that granted the identity names only its new
    common name, the holder's host refuses to render from the old leaf, and the steps name both hosts."""
    layout = load_layout(THREE_SITES)
    pki = tmp_path / "pki"
    init_pki(pki, layout.all_identities(), layout.certificate_names())
    stale = tmp_path / "stale"
    bundle_host(layout, "site1", pki, stale)
    pki_module.revoke(pki, "mec-agent1")
    acl = get(
        zenoh.Config.from_json5(identity_config(layout, "site1", "router-agent1", pki)), "access_control"
    )
    names = {n for subject in acl["subjects"] for n in subject["cert_common_names"]}
    assert "mec-agent1.1" in names and "mec-agent1" not in names
    assert "sensor-agent1-cameras" in names  # the others unchanged
    with pytest.raises(ConfigError, match="revoked"):
        render_host(layout, "site1", _with_generations(stale, pki), tmp_path / "out")
    fresh = tmp_path / "fresh"
    bundle_host(layout, "site1", pki, fresh)
    render_host(layout, "site1", fresh, tmp_path / "out")
    assert [s.split(":")[0] for s in revocation_steps(layout, "mec-agent1")] == ["site1"]
    assert [s.split(":")[0] for s in revocation_steps(layout, "router-agent1")] == ["site1", "cloud"]
    with pytest.raises(ConfigError, match="not in the layout"):
        revocation_steps(layout, "mec-agent9")


def _with_generations(bundle: Path, pki: Path) -> Path:
    """A host's old bundle that received the new generations.json but not its new leaf."""
    (bundle / "generations.json").write_bytes((pki / "generations.json").read_bytes())
    return bundle


def test_rmmdet_pki_revoke_names_the_hosts_to_update(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from services.cli.main import app

    layout = load_layout(THREE_SITES)
    init_pki(tmp_path, layout.all_identities(), layout.certificate_names())
    run = CliRunner().invoke(app, ["pki", "revoke", "vehicle-v03", "--dir", str(tmp_path)])
    assert run.exit_code == 0, run.output
    assert "vehicle-v03.1" in run.output and "vehicles: rmmdet pki bundle" in run.output
    assert "cloud: rmmdet pki bundle --host cloud" in run.output  # the router granting it
    run = CliRunner().invoke(app, ["pki", "revoke", "vehicle-zz", "--dir", str(tmp_path)])
    assert run.exit_code == 2 and "not in the layout" in run.output


def test_a_shard_host_holds_its_own_plan_key_and_the_others_public_halves(tmp_path: Path) -> None:
    """Issue 52 item 2: every shard signed with the one plan key. Each shard's host now holds only its
    own shard's private key and every trusted public key (to check the other shards' messages)."""
    layout_file = tmp_path / "layout.yaml"
    layout_file.write_text(
        json.dumps(
            {
                "hosts": {
                    "cloud": {
                        "address": "127.0.0.1",
                        "router": "router-cloud",
                        "services": ["coordinator-region0"],
                    },
                    "east": {"address": "127.0.0.2", "services": ["coordinator-region1"]},
                }
            }
        )
    )
    layout = load_layout(layout_file)
    pki = tmp_path / "pki"
    init_pki(pki, layout.all_identities(), layout.certificate_names())
    east = {p.name for p in bundle_host(layout, "east", pki, tmp_path / "east")}
    assert "plan-signing.region1.key" in east
    assert not {"plan-signing.region0.key", "plan-signing.key"} & east
    assert {"plan-signing.pub", "plan-signing.region0.pub", "plan-signing.region1.pub"} <= east

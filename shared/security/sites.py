"""A multi-host deployment (`deploy/sites/*.yaml`) rendered into each identity's Zenoh config.

Topology: the cloud host's router (`router-cloud`) listens on the cloud address; a roadside site's
router listens on loopback for its own sensor groups and MEC and connects out to the cloud router; a
host without a router (the vehicles) connects its clients to the cloud router. Every link is TLS with
client certificates (mutual), names verified against the certificates' SANs; every router enforces the
access control generated from proto/streams.yaml (`acl.access_control`), with the other router of a
link as one subject holding its side's grants.

The configs are complete JSON files (the base `deploy/zenoh/{router,client}.json5` with endpoints, TLS
and access control filled in), passed to the services with the standard `--config` flag.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import sys
from pathlib import Path
from typing import Any

import zenoh
from cryptography import x509
from pydantic import BaseModel, ConfigDict, Field, model_validator

from shared.bus.streams import sensor_group
from shared.bus.zenoh_config import DEFAULT_CLIENT_CONFIG, DEFAULT_ROUTER_CONFIG
from shared.config import ConfigError, read_yaml
from shared.paths import DEPLOY_DIR, REPO_ROOT
from shared.security.acl import access_control
from shared.security.identities import (
    CLOUD_ROUTER,
    is_router,
    parse_identity,
    router_loopback,
    shard_region,
    vehicle_identity,
)
from shared.security.pki import (
    GENERATIONS_FILE,
    PRIVATE_MODE,
    PUBLIC_MODE,
    RENEW_WITHIN_DAYS,
    ca_paths,
    certificate_name,
    common_name,
    current_common_names,
    days_left,
    generations,
    identity_paths,
    plan_key_paths,
    shard_key_path,
    trusted_plan_keys,
    write_file,
)
from shared.supervision.programs import Program, render_program

log = logging.getLogger(__name__)

DEFAULT_LAYOUT = DEPLOY_DIR / "sites" / "three-sites.yaml"

#: Zenoh link settings of a deployment across hosts (router <-> router and client <-> router).
LINK_SETTINGS: dict[str, Any] = {
    # A silently dropped link (a cut cable, a firewall) is declared dead after `lease` with no
    # traffic; keep-alives go out `keep_alive` times per lease. 1 s: an agent goes STALE at the
    # coordinator within 1 s of a cut (its object lists stop), its presence token within ~1 s.
    "transport/link/tx/lease": 1000,
    "transport/link/tx/keep_alive": 4,
}
#: A router connecting out to the cloud retries quickly and forever (a site must come back by itself).
RECONNECT: dict[str, Any] = {
    "connect/timeout_ms": {"router": -1, "peer": -1, "client": 0},
    "connect/exit_on_failure": {"router": False, "peer": False, "client": False},
    "connect/retry": {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2},
}


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ServiceSpec(_Strict):
    identity: str
    command: list[str] | None = Field(None, description="python arguments; default from the identity")
    env: dict[str, str] = Field({}, description="extra environment (settings overrides)")


class HostSpec(_Strict):
    address: str
    router: str | None = None
    services: list[str | ServiceSpec] = []
    vehicles: list[str] = Field(
        [], description="ids of the vehicles the host's sim drives, each under its own identity vehicle-<id>"
    )

    @model_validator(mode="after")
    def _check(self) -> HostSpec:
        ipaddress.ip_address(self.address)
        if self.router is not None and parse_identity(self.router).grants[0].role != "router":
            raise ValueError(f"router {self.router!r} is not a router identity")
        if self.vehicles and "sim" not in [s.identity for s in self.service_specs()]:
            raise ValueError("vehicles are listed on a host without the sim that drives them")
        for vehicle_id in self.vehicles:
            vehicle_identity(vehicle_id)
        return self

    def service_specs(self) -> list[ServiceSpec]:
        return [s if isinstance(s, ServiceSpec) else ServiceSpec(identity=s) for s in self.services]


class Layout(_Strict):
    port: int = Field(7447, gt=0, lt=65536)
    hosts: dict[str, HostSpec]

    @model_validator(mode="after")
    def _check(self) -> Layout:
        clouds = [h for h, spec in self.hosts.items() if spec.router == CLOUD_ROUTER]
        if len(clouds) != 1:
            raise ValueError(f"exactly one host must run {CLOUD_ROUTER}, got {clouds}")
        seen: set[str] = set()
        for spec in self.hosts.values():
            for identity in [s.identity for s in spec.service_specs()] + [
                vehicle_identity(v) for v in spec.vehicles
            ]:
                parse_identity(identity)
                if identity in seen:
                    raise ValueError(f"identity {identity} twice in the layout")
                seen.add(identity)
        return self

    @property
    def cloud_host(self) -> str:
        return next(h for h, spec in self.hosts.items() if spec.router == CLOUD_ROUTER)

    def endpoint(self, address: str) -> str:
        return f"tls/{address}:{self.port}"

    def identities(self, host: str) -> list[str]:
        spec = self.hosts[host]
        services = [s.identity for s in spec.service_specs()]
        return ([spec.router] if spec.router else []) + services + self.vehicle_identities(host)

    def vehicle_identities(self, host: str) -> list[str]:
        return [vehicle_identity(v) for v in self.hosts[host].vehicles]

    def all_identities(self) -> list[str]:
        return ["operator", *(i for h in self.hosts for i in self.identities(h))]

    def certificate_names(self) -> dict[str, tuple[str, ...]]:
        """Extra SANs: the cloud router is reached by its address."""
        return {CLOUD_ROUTER: (self.hosts[self.cloud_host].address,)}


def load_layout(path: Path) -> Layout:
    try:
        return Layout.model_validate(read_yaml(path))
    except (ValueError, ConfigError) as err:
        raise ConfigError(f"{path}: invalid site layout: {err}") from None


def router_subjects(layout: Layout, host: str) -> dict[str, list[str]]:
    """Identity connecting to `host`'s router -> the identities whose grants it holds."""
    spec = layout.hosts[host]
    subjects = {i: [i] for i in layout.identities(host) if i != spec.router}
    if host == layout.cloud_host:
        subjects["operator"] = ["operator"]
        for other, other_spec in layout.hosts.items():
            if other == host:
                continue
            if other_spec.router:  # a site: its router speaks for its identities
                subjects[other_spec.router] = layout.identities(other)
            else:  # a host without a router: its identities connect to the cloud's one by one
                subjects.update({i: [i] for i in layout.identities(other)})
    else:  # the cloud router speaks for everyone not at this site
        subjects[CLOUD_ROUTER] = [i for i in layout.all_identities() if i not in layout.identities(host)]
    return subjects


def revocation_steps(layout: Layout, identity: str) -> list[str]:
    """What to do on which host after `pki.revoke(identity)`: the holder's host takes its new bundle,
    and every router that grants `identity` (`router_subjects`) is rendered again and restarted."""
    holders = [h for h in layout.hosts if identity in layout.identities(h)]
    routers = [h for h in layout.hosts if layout.hosts[h].router and identity in router_subjects(layout, h)]
    if not holders and identity != "operator":
        raise ConfigError(f"{identity}: not in the layout (hosts: {sorted(layout.hosts)})")
    steps = [f"{h}: rmmdet pki bundle --host {h} (the new key of {identity}), restart it" for h in holders]
    steps += [
        f"{h}: rmmdet pki bundle --host {h} (generations.json), render and restart {layout.hosts[h].router}"
        for h in routers
        if h not in holders
    ]
    return steps


def tls_settings(pki_dir: Path, identity: str) -> dict[str, Any]:
    paths = identity_paths(pki_dir, identity)
    return {
        "root_ca_certificate": str(ca_paths(pki_dir).cert),
        "enable_mtls": True,
        "listen_certificate": str(paths.cert),
        "listen_private_key": str(paths.key),
        "connect_certificate": str(paths.cert),
        "connect_private_key": str(paths.key),
        "verify_name_on_connect": True,
        "close_link_on_expiration": True,
    }


def _config(base: Path, settings: dict[str, Any]) -> str:
    conf = zenoh.Config.from_file(str(base))
    for key, value in settings.items():
        conf.insert_json5(key, json.dumps(value))
    return str(conf)


def identity_config(layout: Layout, host: str, identity: str, pki_dir: Path) -> str:
    """The complete Zenoh config (JSON) of `identity` on `host`."""
    spec = layout.hosts[host]
    cloud = layout.hosts[layout.cloud_host]
    settings: dict[str, Any] = {**LINK_SETTINGS, "transport/link/tls": tls_settings(pki_dir, identity)}
    if identity == spec.router:
        loopback = router_loopback(identity)
        listen = [layout.endpoint(loopback)]
        if host == layout.cloud_host and spec.address != loopback:
            listen.insert(0, layout.endpoint(spec.address))
        settings["listen/endpoints"] = listen
        if host != layout.cloud_host:
            settings["connect/endpoints"] = [layout.endpoint(cloud.address)]
            settings.update(RECONNECT)
        settings["access_control"] = access_control(
            router_subjects(layout, host), current_common_names(pki_dir)
        )
        return _config(DEFAULT_ROUTER_CONFIG, settings)
    router_address = router_loopback(spec.router) if spec.router else cloud.address
    settings["connect/endpoints"] = [layout.endpoint(router_address)]
    return _config(DEFAULT_CLIENT_CONFIG, settings)


def default_command(identity: str) -> list[str]:
    """`python` arguments of the service an identity names."""
    grant = parse_identity(identity).grants[0]
    b = grant.bindings
    if grant.role == "sensors":
        return ["-m", "services.sensor", "--group", sensor_group(b["agent"], b["kind"])]
    if grant.role == "mec":
        return ["-m", "services.mec", "--instance", b["agent"]]
    if grant.role == "router":
        return ["-m", "services.router"]
    if grant.role == "coordinator" and "region" in b:  # a shard: the layout's env names the region map
        return ["-m", "services.coordinator", "--shard", b["region"]]
    if identity in ("sim", "coordinator", "recorder"):
        return ["-m", f"services.{identity}"]
    raise ConfigError(f"identity {identity}: no service to run (give `command` in the layout)")


def signing_key(identity: str, pki_dir: Path) -> Path | None:
    """The plan key `identity` signs with: the coordinator's, a shard's own (`pki.shard_key_path`),
    None for an identity that signs nothing."""
    if parse_identity(identity).grants[0].role != "coordinator":
        return None
    region = shard_region(identity)
    key = plan_key_paths(pki_dir).key
    return key if region is None else shard_key_path(key, region)


def service_environment(identity: str, pki_dir: Path) -> dict[str, str]:
    """Settings a service needs from the PKI besides its TLS identity (plan keys: a shard finds its own
    beside the coordinator's, `pki.shard_key_path`)."""
    if signing_key(identity, pki_dir) is not None:
        return {"RMMDET_COORD_PLAN_SIGNING_KEY": str(plan_key_paths(pki_dir).key)}
    if identity == "sim":
        return {"RMMDET_SIM_PLAN_VERIFY_KEYS": json.dumps([str(p) for p in trusted_plan_keys(pki_dir)])}
    return {}


def check_certificate(pki_dir: Path, identity: str, address: str | None = None) -> None:
    """The identity's certificate exists, has not expired (warned `RENEW_WITHIN_DAYS` ahead), and names
    `address` when peers reach it there (a router's also its own loopback address)."""
    path = identity_paths(pki_dir, identity).cert
    try:
        cert = x509.load_pem_x509_certificate(path.read_bytes())
    except (OSError, ValueError) as err:
        raise ConfigError(f"{path}: no certificate for {identity} ({err}); run `rmmdet pki init`") from None
    expected = certificate_name(identity, generations(pki_dir).get(identity, 0))
    if (cn := common_name(path)) != expected:
        raise ConfigError(
            f"{path}: {identity}'s certificate {cn!r} was revoked (now {expected!r}): give this host its"
            " new bundle (rmmdet pki bundle)"
        )
    left = days_left(cert)
    if left <= 0:
        raise ConfigError(f"{path}: {identity}'s certificate expired; renew it: rmmdet pki init --renew")
    if left <= RENEW_WITHIN_DAYS:
        log.warning(
            "%s: %s's certificate expires in %.0f days: rmmdet pki init --renew", path, identity, left
        )
    needed = ([router_loopback(identity)] if is_router(identity) else []) + ([address] if address else [])
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    for ip in needed:
        if ipaddress.ip_address(ip) not in san.get_values_for_type(x509.IPAddress):
            fix = "rmmdet pki init --renew" + (f" --name {identity}={address}" if address else "")
            raise ConfigError(f"{path}: does not name {ip}; reissue it: {fix}")


def supervisor_program(name: str, args: list[str], config: Path, env: dict[str, str], logs: Path) -> str:
    """The host's program `name`: `args` with its Zenoh `--config`, its `env` (plan keys, the layout's)."""
    program = Program(name, [*args, "--config", str(config)], env=env)
    return render_program(program, python=sys.executable, directory=REPO_ROOT, logs=logs)


def write_vehicle_configs(layout: Layout, host: str, pki_dir: Path, out_dir: Path) -> Path:
    """The Zenoh config of each vehicle identity on `host`, as `<dir>/vehicle-<id>.json` (what the sim's
    `--vehicle-configs` reads); returns the directory."""
    vehicles_dir = out_dir / "vehicles"
    vehicles_dir.mkdir(parents=True, exist_ok=True)
    for identity in layout.vehicle_identities(host):
        (vehicles_dir / f"{identity}.json").write_text(identity_config(layout, host, identity, pki_dir))
    return vehicles_dir


def _host_spec(layout: Layout, host: str) -> HostSpec:
    if host not in layout.hosts:
        raise ConfigError(f"no host {host!r} in the layout (hosts: {sorted(layout.hosts)})")
    return layout.hosts[host]


def host_files(layout: Layout, host: str, pki_dir: Path) -> list[Path]:
    """What of the PKI `host` needs, and nothing more: the CA's certificate (never its key), the leaf and
    key of each identity it runs (its vehicles' included), the plan key's private half where the
    coordinator signs and the trusted public halves where vehicles verify."""
    _host_spec(layout, host)
    identities = layout.identities(host)
    files = [ca_paths(pki_dir).cert]
    if (pki_dir / GENERATIONS_FILE).exists():  # revoked leaves: routers grant only their successors
        files.append(pki_dir / GENERATIONS_FILE)
    for identity in identities:
        paths = identity_paths(pki_dir, identity)
        files += [paths.cert, paths.key]
    files += [k for i in identities if (k := signing_key(i, pki_dir)) is not None]
    if "sim" in identities or any(shard_region(i) is not None for i in identities):  # verify others' keys
        files += trusted_plan_keys(pki_dir)
    return files


def bundle_host(layout: Layout, host: str, pki_dir: Path, out_dir: Path) -> list[Path]:
    """Copy `host_files` to `out_dir` (private keys mode 0600), the directory to give that host as its
    `--pki`; returns the copies. The CA key stays where certificates are made (issue 34 item 3)."""
    if out_dir.resolve() == pki_dir.resolve():
        raise ConfigError(f"{out_dir}: the bundle must go to another directory than the PKI itself")
    out_dir.mkdir(parents=True, exist_ok=True)
    copies = []
    for src in host_files(layout, host, pki_dir):
        if not src.exists():
            raise ConfigError(
                f"{src}: missing from the PKI; run `rmmdet pki init` (with the layout's identities)"
            )
        dst = out_dir / src.name
        private = src.suffix == ".key"
        write_file(dst, src.read_bytes(), PRIVATE_MODE if private else PUBLIC_MODE)
        copies.append(dst)
    return copies


def refuse_ca_key(pki_dir: Path) -> None:
    """A service host must not hold the CA's private key: whoever takes that host could issue any
    identity. The launcher runs only from a host bundle (`rmmdet pki bundle`)."""
    ca_key = ca_paths(pki_dir).key
    if ca_key.exists():
        raise ConfigError(
            f"{ca_key}: the CA's private key is in this host's PKI directory; no service host may hold it."
            " Give the host its bundle instead: rmmdet pki bundle --host HOST --out DIR (then --pki DIR)"
        )


def render_host(layout: Layout, host: str, pki_dir: Path, out_dir: Path) -> Path:
    """Write `host`'s configs and its supervisord.conf under `out_dir`; returns the latter. Refuses a PKI
    directory holding the CA key (`refuse_ca_key`)."""
    spec = _host_spec(layout, host)
    refuse_ca_key(pki_dir)
    for identity in layout.identities(host):
        address = spec.address if identity == CLOUD_ROUTER else None
        check_certificate(pki_dir, identity, address)
    out_dir.mkdir(parents=True, exist_ok=True)
    logs = out_dir / "logs"
    logs.mkdir(exist_ok=True)
    programs = []
    runs = ([ServiceSpec(identity=spec.router)] if spec.router else []) + spec.service_specs()
    for svc in runs:
        config = out_dir / f"{svc.identity}.json"
        config.write_text(identity_config(layout, host, svc.identity, pki_dir))
        env = {**service_environment(svc.identity, pki_dir), **svc.env}
        args = svc.command or default_command(svc.identity)
        if svc.identity == "sim" and spec.vehicles:
            args = [*args, "--vehicle-configs", str(write_vehicle_configs(layout, host, pki_dir, out_dir))]
        programs.append(supervisor_program(svc.identity, args, config, env, logs))
    conf = out_dir / "supervisord.conf"
    conf.write_text(
        f"""; generated by `python -m deploy.sites.launch --host {host}`: do not edit, edit the layout
[unix_http_server]
file={out_dir / "supervisor.sock"}

[supervisord]
logfile={logs / "supervisord.log"}
pidfile={out_dir / "supervisord.pid"}
childlogdir={logs}
directory={REPO_ROOT}
nodaemon=true

[rpcinterface:supervisor]
supervisor.rpcinterface_factory = supervisor.rpcinterface:make_main_rpcinterface

[supervisorctl]
serverurl=unix://{out_dir / "supervisor.sock"}

"""
        + "\n".join(programs)
    )
    return conf

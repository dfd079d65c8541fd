"""Who is who in a secure deployment: identity names (certificate CNs) and what each one is.

An identity's name says its role and the key bindings it is confined to:

    router                      the one-host router (`make up`)
    router-cloud                the cloud router (coordinator, recorder, operator, sim connect here)
    router-<agent>              a roadside site's router (that agent's sensor groups and MEC)
    sensor-<agent>-<kind>s      one sensor group: publishes only <agent>'s <kind> sensor keys
    mec-<agent>                 agent <agent>'s edge process
    coordinator, recorder, operator (the `rmmdet` tool), sim (the world: clock, ground truth, calibration)
    vehicle-<id>                one connected vehicle: requests, receives and acks only its own plans
                                (the sim's vehicles too: it drives each under that vehicle's identity)

`proto/streams.yaml` says which role publishes, subscribes, serves or queries each stream; the access
control rules (`shared/security/acl.py`) are those grants with each identity's bindings filled in.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Sequence
from dataclasses import dataclass, field

from shared.bus import names
from shared.bus.streams import sensor_group, shard_instance
from shared.config import ConfigError
from shared.scene.scene import Scene

ROLES = ("router", "sim", "vehicles", "sensors", "mec", "coordinator", "recorder", "operator")
#: The `service` part of each role's health and presence keys (`rmmdet/v1/{scope}/@alive/{service}/..`).
SERVICE_OF_ROLE = {
    "router": names.ROUTER,
    "sim": names.SIM,
    "sensors": names.SENSOR,
    "mec": names.MEC,
    "coordinator": names.COORDINATOR,
    "recorder": names.RECORDER,
}
SENSOR_KINDS = ("camera", "lidar", "radar")
CLOUD_ROUTER = "router-cloud"
LOCAL_ROUTER = "router"
_SENSOR_RE = re.compile(r"^sensor-(?P<agent>[a-z0-9_]+)-(?P<kind>camera|lidar|radar)s$")
_AGENT_RE = re.compile(r"^(?P<role>mec|router)-(?P<agent>[a-z0-9_]+)$")
_VEHICLE_RE = re.compile(r"^vehicle-(?P<vehicle>[A-Za-z0-9_]+)$")
#: A coordinator shard (services/coordinator/shard.py): publishes only its own region's maps and clique.
_SHARD_RE = re.compile(r"^coordinator-region(?P<region>[0-9]+)$")


@dataclass(frozen=True)
class Grant:
    """One role an identity holds, with the key placeholders it is confined to (unbound: any)."""

    role: str
    bindings: dict[str, str] = field(default_factory=dict)

    def __hash__(self) -> int:
        return hash((self.role, tuple(sorted(self.bindings.items()))))


@dataclass(frozen=True)
class Identity:
    name: str
    grants: tuple[Grant, ...]


def parse_identity(name: str) -> Identity:
    """The grants an identity name stands for; ConfigError for a name that is none of the above."""
    if name in ("coordinator", "recorder", "operator"):
        return Identity(name, (Grant(name),))
    if name == "sim":  # the world; the vehicles it drives each have their own identity
        return Identity(name, (Grant("sim"),))
    if name in (LOCAL_ROUTER, CLOUD_ROUTER):
        return Identity(name, (Grant("router"),))
    if m := _SENSOR_RE.match(name):
        return Identity(name, (Grant("sensors", {"agent": m["agent"], "kind": m["kind"]}),))
    if m := _AGENT_RE.match(name):
        if m["role"] == "mec":
            return Identity(name, (Grant("mec", {"agent": m["agent"]}),))
        return Identity(name, (Grant("router", {"site": m["agent"]}),))
    if m := _VEHICLE_RE.match(name):
        return Identity(name, (Grant("vehicles", {"vehicle": m["vehicle"]}),))
    if m := _SHARD_RE.match(name):
        return Identity(name, (Grant("coordinator", {"region": m["region"]}),))
    raise ConfigError(f"identity {name!r}: not a known role (see shared/security/identities.py)")


def vehicle_identity(vehicle_id: str) -> str:
    """The identity of the vehicle `vehicle_id`."""
    name = f"vehicle-{vehicle_id}"
    if not _VEHICLE_RE.match(name):
        raise ConfigError(f"vehicle id {vehicle_id!r}: letters, digits and _ only")
    return name


def own_instance(grant: Grant) -> str:
    """The instance chunk of a node's own health and presence keys under `grant` (`*`: any): a sensor
    group's is its group (`agent1-cameras`), a MEC's its agent, so a sibling of the same role cannot
    hold another's token or answer for its health. The other roles have one identity each."""
    b = grant.bindings
    if grant.role == "sensors" and "agent" in b and "kind" in b:
        return sensor_group(b["agent"], b["kind"])
    if grant.role == "mec" and "agent" in b:
        return b["agent"]
    if grant.role == "coordinator" and "region" in b:
        return shard_instance(b["region"])
    return "*"


def shard_region(name: str) -> int | None:
    """The region of a coordinator shard's identity (`coordinator-region<k>`), else None."""
    m = _SHARD_RE.match(name)
    return int(m["region"]) if m else None


def shard_identity(region: int) -> str:
    return f"coordinator-region{region}"


def router_loopback(name: str) -> str:
    """The loopback address router `name` listens on for the services of its own host, and the only
    one its certificate names besides its extra names: each router its own (a hash of its name in
    127.0.0.0/8), so a router's stolen key cannot serve another router's clients on their host's
    loopback while that router restarts (every router's certificate named 127.0.0.1: issue 52
    item 9). The one-host router keeps 127.0.0.1."""
    if name == LOCAL_ROUTER:
        return "127.0.0.1"
    digest = hashlib.sha256(name.encode()).digest()
    return f"127.{digest[0]}.{digest[1]}.{1 + digest[2] % 254}"


def is_router(name: str) -> bool:
    """Whether identity `name` is a router's (the only identities that listen for TLS links)."""
    m = _AGENT_RE.match(name)
    return name in (LOCAL_ROUTER, CLOUD_ROUTER) or (m is not None and m["role"] == "router")


def sensor_group_identity(group: str) -> str:
    """`agent1-cameras` -> `sensor-agent1-cameras`."""
    return f"sensor-{group}"


def site_identities(scene: Scene, agent: str) -> list[str]:
    """The identities at one roadside site: its router, its sensor groups and its MEC."""
    kinds = sorted({s.kind for s in scene.sensors_of(agent)})
    groups = [sensor_group_identity(sensor_group(agent, k)) for k in kinds]
    return [f"router-{agent}", *groups, f"mec-{agent}"]


def deployment_identities(scene: Scene, vehicles: Sequence[str] = (), shards: int = 1) -> list[str]:
    """Every identity of the multi-site deployment of `scene` (and the one-host router), with the
    connected `vehicles`' (their ids) and, for a coordinator of `shards` > 1 shards, each shard's."""
    names = [LOCAL_ROUTER, CLOUD_ROUTER, "sim", "coordinator", "recorder", "operator"]
    if shards > 1:
        names += [shard_identity(k) for k in range(shards)]
    for agent in scene.agents:
        names += site_identities(scene, agent)
    return names + [vehicle_identity(v) for v in vehicles]

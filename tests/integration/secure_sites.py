"""Helpers for the secure-deployment tests and benchmark: a layout rendered with a fresh PKI, identity
sessions, a receiver that records what reaches it, and the five-host deployment in network namespaces."""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import yaml
import zenoh
from rmmdet.v1.planning_pb2 import AckStatus

from shared.bus.node import Node, Subscription
from shared.bus.session import open_session
from shared.security.pki import init_pki
from shared.security.sites import Layout, bundle_host, identity_config, load_layout
from sim.config import fleet_ids
from tests.helpers import REPO_ROOT, Router, spawn, stop, wait_until
from tests.integration import netns
from tests.integration.coordinator_client import MapLog

SESSION_TIMEOUT_S = 10.0


@dataclass
class Deployment:
    """A rendered layout: `config(identity)` is what `deploy/sites/launch.py` gives that service."""

    layout: Layout
    pki: Path
    out: Path

    def host_of(self, identity: str) -> str:
        """The host an identity runs on (the operator and strangers: the cloud)."""
        hosts = [h for h in self.layout.hosts if identity in self.layout.identities(h)]
        return hosts[0] if hosts else self.layout.cloud_host

    def config(self, identity: str, host: str | None = None) -> zenoh.Config:
        text = identity_config(self.layout, host or self.host_of(identity), identity, self.pki)
        return zenoh.Config.from_json5(text)

    def session(self, identity: str, host: str | None = None) -> zenoh.Session:
        return open_session(self.config(identity, host), timeout_s=SESSION_TIMEOUT_S)


def make_deployment(tmp: Path, layout: dict, extra_identities: tuple[str, ...] = ()) -> Deployment:
    path = tmp / "layout.yaml"
    path.write_text(yaml.safe_dump(layout))
    loaded = load_layout(path)
    pki = tmp / "pki"
    init_pki(pki, [*loaded.all_identities(), *extra_identities], loaded.certificate_names())
    return Deployment(loaded, pki, tmp / "out")


@dataclass
class Inbox:
    """Every sample (key, payload) a subscription received, thread-safe."""

    samples: list[tuple[str, bytes]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.samples.append((str(sample.key_expr), sample.payload.to_bytes()))

    def keys(self) -> set[str]:
        with self.lock:
            return {k for k, _ in self.samples}

    def payloads(self, key: str) -> list[bytes]:
        with self.lock:
            return [p for k, p in self.samples if k == key]


# --- five hosts in network namespaces (tests/integration/test_secure_sites.py, tests/bench/sites_bench.py)

AGENTS = ("agent1", "agent2", "agent3")
#: Last octet of each host's address on the bridge.
OCTETS = {"cloud": 10, "site1": 11, "site2": 12, "site3": 13, "vehicles": 20}


def five_host_layout(hosts: netns.NetHosts, vehicles: int = 10) -> dict:
    """Three sites with a stand-in MEC each (tests/integration/fake_mec.py), the cloud with the real
    coordinator, the vehicles' host with the real sim driving `vehicles` connected vehicles (route policy
    plan), each on its own identity."""
    sites = {
        f"site{i}": {
            "address": hosts.address(f"site{i}"),
            "router": f"router-agent{i}",
            "services": [
                {
                    "identity": f"mec-agent{i}",
                    "command": ["-m", "tests.integration.fake_mec", "--instance", f"agent{i}"],
                }
            ],
        }
        for i in (1, 2, 3)
    }
    return {
        "port": 7447,
        "hosts": {
            "cloud": {
                "address": hosts.address("cloud"),
                "router": "router-cloud",
                "services": [{"identity": "coordinator", "env": {"RMMDET_COORD_REPLAN_INTERVAL_S": "0.5"}}],
            },
            **sites,
            "vehicles": {
                "address": hosts.address("vehicles"),
                "services": [
                    {
                        "identity": "sim",
                        "command": ["-m", "services.sim", "--vehicles", str(vehicles)],
                        # The world does not wait for observers on other hosts (pacing reads their data).
                        "env": {
                            "RMMDET_SIM_TRAFFIC__ROUTE_POLICY": "plan",
                            "RMMDET_SIM_PACING__ENABLED": "false",
                        },
                    }
                ],
                "vehicles": fleet_ids(vehicles),
            },
        },
    }


#: The sharded deployment: shard 1 of the coordinator on a host of its own (a client of the cloud router).
SHARD_OCTETS = {**OCTETS, "shard1": 14}
TABLE_REGIONS = REPO_ROOT / "deploy" / "coordinator" / "regions" / "sand_table_2.json"


def sharded_layout(hosts: netns.NetHosts, vehicles: int = 10) -> dict:
    """`five_host_layout` with the coordinator split into the table's two region shards (`make up
    SHARDS=2`'s map): region 0 on the cloud host, region 1 on host `shard1`, each under its own identity
    (`coordinator-region<k>`: it may publish only its own region's maps and clique)."""
    layout = five_host_layout(hosts, vehicles)
    env = {"RMMDET_COORD_REPLAN_INTERVAL_S": "0.5", "RMMDET_COORD_SHARDS__REGIONS": str(TABLE_REGIONS)}
    layout["hosts"]["cloud"]["services"] = [{"identity": "coordinator-region0", "env": env}]
    layout["hosts"]["shard1"] = {
        "address": hosts.address("shard1"),
        "services": [{"identity": "coordinator-region1", "env": env}],
    }
    return layout


@dataclass
class Watch:
    """What an observer sees: maps, acks (plan id -> status), pushed plans, and each object list's
    transit (its publish stamp -> arrival here, wall clock: every host is on this machine's clock)."""

    maps: MapLog = field(default_factory=MapLog)
    acks: dict[str, int] = field(default_factory=dict)
    pushed: set[str] = field(default_factory=set)
    transit_s: list[float] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)
    done: threading.Event = field(default_factory=threading.Event)
    threads: list[threading.Thread] = field(default_factory=list)

    def start(self, node: Node, sharded: bool = False) -> None:
        """`sharded`: the maps are the shards' region maps, each naming its own agents (merged)."""
        subs = {
            name: node.subscribe_stream(name, maxsize=10_000)
            for name in ("route_ack", "route_plan", "objects")
        }
        maps = node.subscribe_stream("region_map" if sharded else "traffic_map", maxsize=1000)
        self.threads = [
            threading.Thread(target=self.maps.consume, args=(maps, self.done, sharded), daemon=True),
            threading.Thread(target=self._consume, args=(subs,), daemon=True),
        ]
        for t in self.threads:
            t.start()

    def _consume(self, subs: dict[str, Subscription]) -> None:
        while not self.done.is_set():
            idle = True
            for name, sub in subs.items():
                item = sub.recv(timeout=0.0)
                if item is None:
                    continue
                idle = False
                with self.lock:
                    if name == "route_ack":
                        self.acks[item.message.plan_id] = item.message.status
                    elif name == "route_plan":
                        self.pushed.add(item.message.plan_id)
                    else:
                        published_ns = item.header.processing[-1].end.ToNanoseconds()
                        self.transit_s.append((item.received_wall_ns - published_ns) / 1e9)
            if idle:
                time.sleep(0.005)

    def stop(self) -> None:
        self.done.set()
        for t in self.threads:
            t.join(2)

    def accepted(self) -> int:
        with self.lock:
            return sum(s == AckStatus.ACK_STATUS_ACCEPTED for s in self.acks.values())

    def unacknowledged_pushes(self) -> set[str]:
        with self.lock:
            return self.pushed - self.acks.keys()

    def transits(self, after: int = 0) -> list[float]:
        with self.lock:
            return self.transit_s[after:]


@dataclass
class Sites:
    hosts: netns.NetHosts
    deployment: Deployment
    watch: Watch
    out: Path
    session: zenoh.Session  # the operator's, on the bridge


def dump_logs(out: Path, lines: int = 15) -> str:
    parts = []
    for log in sorted([*out.glob("*/launcher.log"), *out.glob("*/logs/*.log")]):
        tail = "\n".join(log.read_text(errors="replace").splitlines()[-lines:])
        parts.append(f"--- {log.relative_to(out)}\n{tail}")
    return "\n".join(parts)


@contextlib.contextmanager
def five_hosts(tmp: Path, startup_s: float, vehicles: int = 10, sharded: bool = False) -> Iterator[Sites]:
    """The five hosts up, each by `deploy/sites/launch.py`, watched from the bridge as `operator`;
    yields once every agent is LIVE in the coordinator's maps (AssertionError with the logs if not
    within `startup_s`). Everything is stopped and the namespaces removed on exit. `sharded`: six hosts,
    the coordinator as two shards (`sharded_layout`)."""
    octets = SHARD_OCTETS if sharded else OCTETS
    hosts = netns.NetHosts.create(octets)
    launchers: dict[str, subprocess.Popen] = {}
    node = None
    watch = Watch()
    out = tmp / "out"
    try:
        dep = make_deployment(tmp, (sharded_layout if sharded else five_host_layout)(hosts, vehicles))
        for host in octets:
            (out / host).mkdir(parents=True)
            args = [
                sys.executable,
                "deploy/sites/launch.py",
                "--host",
                host,
                "--layout",
                str(tmp / "layout.yaml"),
            ]
            bundle = out / host / "pki"  # what the host is given: never the CA key (the launcher refuses it)
            bundle_host(dep.layout, host, dep.pki, bundle)
            args += ["--pki", str(bundle), "--out", str(out / host)]
            with (out / host / "launcher.log").open("w") as log:
                launchers[host] = subprocess.Popen(
                    hosts.command(host, args), cwd=REPO_ROOT, start_new_session=True, stdout=log, stderr=log
                )
        conf = dep.config("operator")  # reaching the cloud router over the bridge
        conf.insert_json5("connect/endpoints", json.dumps([dep.layout.endpoint(hosts.address("cloud"))]))
        node = Node(conf, service="test", instance="five-hosts", scope="site")
        node.open()
        watch.start(node, sharded)
        try:
            watch.maps.wait(lambda s: all(s.get(a) == "LIVE" for a in AGENTS), startup_s, since=0.0)
        except AssertionError as err:
            raise AssertionError(f"{err}\n{dump_logs(out)}") from None
        yield Sites(hosts, dep, watch, out, node.session)
        exited = [h for h, p in launchers.items() if p.poll() is not None]
        assert not exited, f"launchers exited: {exited}\n{dump_logs(out)}"
    finally:
        watch.stop()
        if node is not None:
            node.close()
        for proc in launchers.values():
            stop(proc, signal.SIGTERM, timeout_s=15)
        hosts.destroy()


def loopback_transits(router: Router, samples: int, timeout_s: float) -> list[float]:
    """The same stand-in MEC's object-list transits through one plain router on loopback."""
    mec = spawn(["-m", "tests.integration.fake_mec", "--instance", "agent1", *router.client_args()])
    watch = Watch()
    node = Node(router.client_config(), service="test", instance="loopback", scope="site")
    node.open()
    try:
        watch.start(node)
        wait_until(lambda: len(watch.transits()) >= samples, timeout_s, "loopback object lists")
    finally:
        watch.stop()
        node.close()
        stop(mec)
    return watch.transits()[:samples]

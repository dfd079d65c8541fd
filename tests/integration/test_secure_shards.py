"""The table's coordinator split in two region shards on the multi-site profile (issue 37): six hosts in
network namespaces (three sites, the vehicles, the cloud with shard 0, host `shard1` with shard 1), every
link mutual TLS, every router enforcing the generated access control, each shard under its own identity
(`coordinator-region<k>`, confined to its own region's keys). Brought up by the documented launcher
(tests/integration/secure_sites.py `five_hosts(sharded=True)`).

- vehicles crossing the boundary get their plans from the new shard and acknowledge them (the shards'
  counters: handovers adopted, acknowledgements accepted, by both);
- shard 1's host cut for 10 s (nftables drop, both ways): shard 0 says region 1 is planned on a prior
  (DEGRADED) and keeps serving: its agents LIVE throughout, its plans still served and acknowledged;
  after the cut shard 1 answers again and shard 0 is NOMINAL.

Needs root, iproute2 and nftables (`make install` / `.ci/run` install them).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator

import pytest
from rmmdet.v1.health_pb2 import HealthLevel, ServiceHealth

from shared.bus.streams import shard_instance
from tests.helpers import wait_until
from tests.integration import netns
from tests.integration.coordinator_client import coordinator_health, counters
from tests.integration.secure_sites import Sites, five_hosts

UNAVAILABLE = netns.available()
pytestmark = [
    pytest.mark.integration,
    pytest.mark.fault,
    pytest.mark.timeout(300),
    pytest.mark.skipif(UNAVAILABLE is not None, reason=f"network namespaces: {UNAVAILABLE}"),
]

SCALE = float(os.environ.get("RSP_TIME_SCALE", "1"))
STARTUP_S = 90.0 * SCALE
CUT_S = 10.0
PRIOR_WITHIN_S = 5.0 * SCALE  # shard 1's presence lost, or its clique stale (3 s)
BACK_WITHIN_S = 15.0 * SCALE  # TLS links re-established after the cut
REGION0_AGENTS = ("agent2", "agent3")  # deploy/coordinator/regions/sand_table_2.json


@pytest.fixture(scope="module")
def sites(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Sites]:
    with five_hosts(tmp_path_factory.mktemp("shards"), STARTUP_S, sharded=True) as s:
        yield s


def health(sites: Sites, region: int) -> ServiceHealth | None:
    return coordinator_health(sites.session, instance=shard_instance(region))


def counter(sites: Sites, region: int, name: str) -> int:
    report = health(sites, region)
    return counters(report).get(name, 0) if report is not None else 0


def message(sites: Sites, region: int) -> str:
    report = health(sites, region)
    return report.message if report is not None else ""


def nominal(sites: Sites, region: int) -> bool:
    report = health(sites, region)
    return report is not None and report.level == HealthLevel.HEALTH_LEVEL_NOMINAL


def test_crossing_vehicles_get_and_acknowledge_plans_from_the_new_shard(sites: Sites) -> None:
    for region in (0, 1):
        for name in ("handovers/adopted", "acks/accepted"):
            wait_until(lambda r=region, n=name: counter(sites, r, n) >= 1, 60 * SCALE, f"{name} on {region}")
    for region in (0, 1):
        report = health(sites, region)
        assert report is not None
        c = counters(report)
        assert c.get("handovers/extra_holder", 0) == 0 and c.get("rejected/handover", 0) == 0, c


def test_a_cut_shard_affects_only_its_region(sites: Sites) -> None:
    maps, watch = sites.watch.maps, sites.watch
    wait_until(lambda: nominal(sites, 0), 30 * SCALE, "shard 0 NOMINAL")
    served_before = counter(sites, 0, "plans/served") + counter(sites, 0, "plans/pushed")
    accepted_before = watch.accepted()
    cut_at = time.monotonic()
    sites.hosts.cut("shard1")
    try:
        prior_s = wait_until(
            lambda: "planned on a prior" in message(sites, 0), PRIOR_WITHIN_S, "region 1 on the prior"
        )
        time.sleep(max(0.0, CUT_S - (time.monotonic() - cut_at)))
        during = [states for _, states in maps.since(cut_at)]
        served_during = counter(sites, 0, "plans/served") + counter(sites, 0, "plans/pushed")
    finally:
        sites.hosts.restore("shard1")
    back_at = time.monotonic()
    back_s = wait_until(
        lambda: health(sites, 1) is not None and nominal(sites, 0), BACK_WITHIN_S, "shard 1 back, 0 NOMINAL"
    )
    print(f"cut shard1: region 1 on the prior after {prior_s:.2f} s; back {back_s:.2f} s after the link")
    assert during and all(states.get(a) == "LIVE" for states in during for a in REGION0_AGENTS)
    assert served_during > served_before, "shard 0 stopped serving while shard 1 was cut"
    wait_until(lambda: watch.accepted() > accepted_before, 20 * SCALE, "plans acknowledged after the cut")
    assert back_at - cut_at >= CUT_S

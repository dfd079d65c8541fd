"""Secure multi-site benchmark: the five-host deployment of tests/integration/test_secure_sites.py,
measured longer.

    python -m tests.bench.sites_bench [--samples 600] [--cut-s 10] [--readme]

Needs root, iproute2 and nftables (network namespaces). Measures
- the transit of object lists (publish stamp -> arrival at an operator on the bridge, wall clock)
  across the hosts (site router -> cloud router -> operator: three mutual-TLS links, access control at
  both routers) against the same stand-in MEC through one plain TCP router on loopback, p50 / p95 / p99;
- for each site in turn, a 10 s link cut (nftables drop both ways): time to STALE at the coordinator,
  time to LIVE after the link returns, and whether any other agent left LIVE meanwhile.
Writes `tests/bench/results/sites.json`; `--readme` puts the table in the README (`sites-bench`).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from shared.machine import git_commit, machine_info
from shared.readme import replace_section
from tests.helpers import start_router, stop, wait_until
from tests.integration import netns
from tests.integration.secure_sites import AGENTS, five_hosts, loopback_transits

RESULTS = Path(__file__).resolve().parent / "results" / "sites.json"
STARTUP_S = 120.0
SITES = {"site1": "agent1", "site2": "agent2", "site3": "agent3"}


def percentiles_ms(values: list[float]) -> dict[str, float]:
    a = np.array(values) * 1e3
    return {f"p{q}": round(float(np.percentile(a, q)), 2) for q in (50, 95, 99)} | {"n": len(values)}


def cut_site(sites: Any, site: str, agent: str, cut_s: float) -> dict[str, Any]:
    maps = sites.watch.maps
    maps.wait(lambda s: all(s.get(a) == "LIVE" for a in AGENTS), 30, since=time.monotonic())
    cut_at = time.monotonic()
    sites.hosts.cut(site)
    try:
        stale_at = maps.wait(lambda s: s.get(agent) != "LIVE", cut_s, since=cut_at)
        time.sleep(max(0.0, cut_s - (time.monotonic() - cut_at)))
    finally:
        sites.hosts.restore(site)
    back_at = time.monotonic()
    live_at = maps.wait(lambda s: s.get(agent) == "LIVE", 30, since=back_at)
    others = [a for a in AGENTS if a != agent]
    flips = sum(1 for t, s in maps.since(cut_at) if t <= live_at for a in others if s.get(a) != "LIVE")
    return {
        "site": site,
        "stale_after_s": round(stale_at - cut_at, 2),
        "live_after_return_s": round(live_at - back_at, 2),
        "other_agent_flips": flips,
    }


def run(samples: int, cut_s: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="sites-bench-") as tmp, five_hosts(Path(tmp), STARTUP_S) as sites:
        n0 = len(sites.watch.transits())
        wait_until(lambda: len(sites.watch.transits(n0)) >= samples, 4 * samples / 15 + 30, "object lists")
        secure = sites.watch.transits(n0)[:samples]
        cuts = [cut_site(sites, site, agent, cut_s) for site, agent in SITES.items()]
        wait_until(lambda: not sites.watch.unacknowledged_pushes(), 30, "pushed plans acknowledged")
        with sites.watch.lock:
            pushed, acks = len(sites.watch.pushed), len(sites.watch.acks)
    router = start_router()
    try:
        loopback = loopback_transits(router, samples, 4 * samples / 15 + 30)
    finally:
        stop(router.proc)
    return {
        "commit": git_commit(),
        "machine": machine_info(),
        "transit_ms": {
            "five_hosts_mtls_acl": percentiles_ms(secure),
            "one_loopback_router": percentiles_ms(loopback),
        },
        "cuts": cuts,
        "cut_s": cut_s,
        "plans_pushed": pushed,
        "acks_seen": acks,
    }


def readme_table(r: dict[str, Any]) -> str:
    t = r["transit_ms"]
    secure, lo = t["five_hosts_mtls_acl"], t["one_loopback_router"]
    m = r["machine"]

    def row(name: str, p: dict[str, float]) -> str:
        return f"| {name} | {p['p50']} | {p['p95']} | {p['p99']} | {p['n']} |"

    lines = [
        f"Measured by `python -m tests.bench.sites_bench --readme` at {r['commit']} on {m['cpu_model']} "
        f"({m['cpu_count']} cores; all five hosts are namespaces of this one machine).",
        "",
        "| Object-list transit (publish -> operator), ms | p50 | p95 | p99 | n |",
        "|---|---|---|---|---|",
        row("five hosts: site router -> cloud router -> operator, mutual TLS, access control", secure),
        row("one plain TCP router on loopback (the `make up` profile)", lo),
        f"| cost of the secure multi-site path (p50 difference) | {secure['p50'] - lo['p50']:.2f} | | | |",
        "",
        f"| Site link cut for {r['cut_s']:g} s (nftables drop) | STALE after, s | LIVE after return, s "
        "| other agents leaving LIVE |",
        "|---|---|---|---|",
        *(
            f"| {c['site']} | {c['stale_after_s']} | {c['live_after_return_s']} | {c['other_agent_flips']} |"
            for c in r["cuts"]
        ),
        "",
        f"Plans pushed meanwhile (coverage changes): {r['plans_pushed']}, every one acknowledged.",
    ]
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--samples", type=int, default=600)
    parser.add_argument("--cut-s", type=float, default=10.0)
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--readme", action="store_true")
    args = parser.parse_args()
    reason = netns.available()
    if reason is not None:
        raise SystemExit(f"sites bench: network namespaces unavailable: {reason}")
    result = run(args.samples, args.cut_s)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(readme_table(result))
    if args.readme:
        replace_section("sites-bench", readme_table(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

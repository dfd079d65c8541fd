"""Hosts as Linux network namespaces on one machine, joined by a bridge, with link cuts by nftables.

    hosts = NetHosts.create({"cloud": 10, "site1": 11})   # last octet of each host's address
    proc = hosts.spawn("site1", [python, "deploy/sites/launch.py", ...])
    hosts.cut("site1"); ...; hosts.restore("site1")
    hosts.destroy()

Each namespace gets a veth into a bridge in the root namespace (which holds .1, so the test process can
reach every host); the /24 is chosen from the process id so concurrent runs do not collide. A cut is an
nftables table in the host's namespace dropping everything on its veth both ways (a pulled cable
that the kernel does not report: no RST, no ICMP); a lossy link drops a share of the packets at random
(`nft numgen`, as `tc netem` is not available). Needs root, `ip` (iproute2) and `nft` (nftables).
"""

from __future__ import annotations

import itertools
import os
import shutil
import subprocess
from dataclasses import dataclass, field

CUT_TABLE = "rmmdet_cut"
_CREATED = itertools.count()  # NetHosts made by this process
VETH = "eth0"


def available() -> str | None:
    """None when namespaces can be made here, else why not."""
    if os.geteuid() != 0:
        return "needs root"
    for tool in ("ip", "nft"):
        if shutil.which(tool) is None:
            return f"needs `{tool}` (apt-get install iproute2 nftables)"
    probe = f"rmmprobe{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if made.returncode != 0:
        return f"cannot create a network namespace: {made.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


def _run(*args: str) -> None:
    subprocess.run(list(args), check=True, capture_output=True, text=True)


@dataclass
class NetHosts:
    subnet: str  # "10.77.N"
    tag: str
    octets: dict[str, int]
    bridge: str = ""
    made: list[str] = field(default_factory=list)

    @classmethod
    def create(cls, octets: dict[str, int]) -> NetHosts:
        pid, n = os.getpid(), next(_CREATED)
        # Names unique per creation, not per process: the namespaces a previous creation of this process
        # deleted take their veth pairs with them asynchronously (the kernel's netns cleanup), so reusing a
        # name at once can meet "File exists" on a busy machine.
        hosts = cls(subnet=f"10.77.{(pid + n) % 250 + 1}", tag=f"{pid % 10000}{n % 10}", octets=dict(octets))
        hosts.bridge = f"rmb{hosts.tag}"
        try:
            _run("ip", "link", "add", hosts.bridge, "type", "bridge")
            _run("ip", "addr", "add", f"{hosts.subnet}.1/24", "dev", hosts.bridge)
            _run("ip", "link", "set", hosts.bridge, "up")
            for name, octet in octets.items():
                ns, veth = hosts.namespace(name), f"rmv{hosts.tag}{octet}"
                _run("ip", "netns", "add", ns)
                hosts.made.append(ns)
                _run("ip", "link", "add", veth, "type", "veth", "peer", "name", VETH, "netns", ns)
                _run("ip", "link", "set", veth, "master", hosts.bridge, "up")
                _run("ip", "-n", ns, "addr", "add", f"{hosts.address(name)}/24", "dev", VETH)
                _run("ip", "-n", ns, "link", "set", VETH, "up")
                _run("ip", "-n", ns, "link", "set", "lo", "up")
        except BaseException:
            hosts.destroy()
            raise
        return hosts

    def namespace(self, name: str) -> str:
        return f"rmm{self.tag}-{name}"

    def address(self, name: str) -> str:
        return f"{self.subnet}.{self.octets[name]}"

    def command(self, name: str, args: list[str]) -> list[str]:
        return ["ip", "netns", "exec", self.namespace(name), *args]

    def cut(self, name: str) -> None:
        """Drop every packet on the host's link, both ways, silently."""
        self._filter(name, "drop")

    def lossy(self, name: str, percent: int) -> None:
        """Drop `percent` % of the packets on the host's link, each way, at random (no tc netem here)."""
        self._filter(name, f"numgen random mod 100 < {int(percent)} drop")

    def _filter(self, name: str, verdict: str) -> None:
        """One nftables table in the host's namespace applying `verdict` to its link, in and out."""
        rules = (
            f"table inet {CUT_TABLE} {{\n"
            f"  chain in {{ type filter hook input priority 0; iifname {VETH} {verdict}; }}\n"
            f"  chain out {{ type filter hook output priority 0; oifname {VETH} {verdict}; }}\n"
            "}\n"
        )
        ns = self.namespace(name)
        subprocess.run(["ip", "netns", "exec", ns, "nft", "-f", "-"], input=rules, check=True, text=True)

    def restore(self, name: str) -> None:
        """Undo `cut` or `lossy`."""
        _run("ip", "netns", "exec", self.namespace(name), "nft", "delete", "table", "inet", CUT_TABLE)

    def destroy(self) -> None:
        for ns in self.made:  # deleting a namespace deletes its end of the veth, and so the pair
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        self.made = []
        if self.bridge:
            subprocess.run(["ip", "link", "del", self.bridge], capture_output=True)

"""The README's listener (a plain zenoh-python client on `rmmdet/**`) receives the system's data.

The key space's version is a plain chunk (`rmmdet/v1/...`) so the natural wildcard matches it; control
traffic stays under verbatim chunks (`@alive`, `@health`, `@rpc`) that no data wildcard crosses. The
listener is taken from README.md as written (only the router's port differs) and run beside a bus peer
publishing object lists through the project's Node (which also declares its presence token and health
queryable).
"""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
import zenoh

from shared.bus.streams import get_stream
from shared.paths import REPO_ROOT
from tests.helpers import Router, spawn, stop

pytestmark = [pytest.mark.integration, pytest.mark.timeout(60)]

README_ENDPOINT = "tcp/127.0.0.1:7447"


def readme_listener() -> str:
    """The README's python block that subscribes to `rmmdet/**`."""
    blocks = re.findall(r"```python\n(.*?)```", (REPO_ROOT / "README.md").read_text(), flags=re.S)
    listeners = [b for b in blocks if '"rmmdet/**"' in b]
    assert len(listeners) == 1, "README.md should hold one listener example on rmmdet/**"
    assert README_ENDPOINT in listeners[0]
    return listeners[0]


def test_the_readme_listener_receives_data_and_no_control_traffic(router: Router) -> None:
    script = readme_listener().replace(README_ENDPOINT, router.endpoint)
    peer = ["-m", "tests.integration.bus_peer", "pub", "--count", "400", "--rate-hz", "50"]
    pub = spawn([*peer, *router.client_args()])
    try:
        out = subprocess.run(
            [sys.executable, "-c", script], cwd=REPO_ROOT, capture_output=True, text=True, timeout=30
        )
    finally:
        stop(pub)
    assert out.returncode == 0, out.stderr
    keys = {line.split()[0] for line in out.stdout.splitlines() if line.strip()}
    objects = get_stream("objects").key(agent="agent1")
    assert objects in keys, out.stdout[-2000:]
    assert all(zenoh.KeyExpr(k).intersects(zenoh.KeyExpr("rmmdet/v1/**")) for k in keys)
    assert not [k for k in keys if "/@" in k]  # presence, health, RPC: never data

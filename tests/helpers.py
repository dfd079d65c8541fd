"""Test helpers: paths, free ports, subprocess control, a router subprocess (tests.helpers)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from shared.paths import REPO_ROOT as REPO_ROOT  # re-exported: the tests take it from here

DATA_DIR = Path(__file__).resolve().parent / "data"
TEST_SCENE = DATA_DIR / "test_scene.yaml"
FULL_SCALE_SCENE = REPO_ROOT / "deploy" / "scenes" / "intersection.yaml"  # the real-size site


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_until(pred, timeout_s: float, what: str = "condition", poll_s: float = 0.05) -> float:
    """Poll `pred()` until true; the seconds it took (AssertionError naming `what` after the timeout)."""
    t0 = time.monotonic()
    while not pred():
        assert time.monotonic() - t0 < timeout_s, f"{what} not within {timeout_s} s"
        time.sleep(poll_s)
    return time.monotonic() - t0


def wait_port(port: int, address: str = "127.0.0.1", timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            if s.connect_ex((address, port)) == 0:
                return
        time.sleep(0.05)
    raise TimeoutError(f"nothing listening on {port} after {timeout_s} s")


def spawn(args: list[str], **kwargs) -> subprocess.Popen:
    """Run `python <args>` from the repo root in its own process group."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **kwargs.pop("env", {})}
    return subprocess.Popen(
        [sys.executable, *args],
        cwd=REPO_ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
        **kwargs,
    )


def stop(proc: subprocess.Popen, sig: int = signal.SIGINT, timeout_s: float = 5.0) -> int:
    """Signal the process group, escalate to SIGKILL; return the exit code."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, sig)
            return proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    return proc.wait(timeout_s)


class Router:
    def __init__(self, port: int, proc: subprocess.Popen) -> None:
        self.port = port
        self.proc = proc
        self.endpoint = f"tcp/127.0.0.1:{port}"

    def client_args(self) -> list[str]:
        return ["--connect", self.endpoint]

    def client_config(self):
        from shared.bus.zenoh_config import DEFAULT_CLIENT_CONFIG, zenoh_config

        return zenoh_config(DEFAULT_CLIENT_CONFIG, connect=[self.endpoint])


def start_router(port: int | None = None) -> Router:
    port = port or free_port()
    proc = spawn(["-m", "services.router", "--listen", f"tcp/127.0.0.1:{port}", "--report-interval-s", "0.5"])
    wait_port(port)
    router = Router(port, proc)
    wait_ready(router)
    return router


def wait_ready(router: Router, timeout_s: float = 15.0) -> None:
    """Listening is not ready: wait until the router's presence token is visible (its Node is up)."""
    from shared.bus.liveliness import alive_tokens
    from shared.bus.session import open_session
    from shared.bus.streams import get_stream

    key = get_stream("alive").pattern(scope="site", service="router")
    deadline = time.monotonic() + timeout_s
    with open_session(router.client_config(), timeout_s=timeout_s) as session:
        while time.monotonic() < deadline:
            if alive_tokens(session, key, timeout_s=1.0):
                return
            time.sleep(0.05)
    raise TimeoutError(f"router on {router.port} not ready after {timeout_s} s")


class FakeZBytes:
    """Stands in for zenoh.ZBytes in tests that call Zenoh callbacks directly (payloads, attachments)."""

    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data

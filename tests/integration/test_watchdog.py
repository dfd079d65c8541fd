"""The watchdog under a real supervisord (issue 17: stall detection, crash-loop backoff).

supervisord runs a router, a service whose loop hangs 1.5 s after it starts (alive to Zenoh:
tests/integration/hang_service.py), a program that crashes 1.5 s after every start, and the watchdog
(`services/watchdog`, backoff shortened to 8 s for the test; its default of 30 s is unit-tested):
- the stuck service is restarted within 5 s of its loop stopping;
- the crash loop is held (not running) for the whole backoff once it started 3 times, the watchdog's
  health is DEGRADED naming it meanwhile, and it is started again afterwards.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from rmmdet.v1.health_pb2 import HealthLevel

from services.watchdog.main import supervisor_proxy
from shared.bus.session import open_session
from shared.bus.zenoh_config import DEFAULT_CLIENT_CONFIG, zenoh_config
from shared.supervision.verdict import query_health
from tests.helpers import REPO_ROOT, free_port, stop

pytestmark = [pytest.mark.integration, pytest.mark.fault, pytest.mark.timeout(120)]

SCALE = float(os.environ.get("RSP_TIME_SCALE", "1"))
HANG_AFTER_S = 1.5
BACKOFF_S = 8.0
RESTART_WITHIN_S = 5.0 * SCALE


def program(name: str, command: str, logs: Path) -> str:
    return f"""[program:{name}]
command={command}
directory={REPO_ROOT}
autorestart=true
startsecs=1
startretries=1000
stopsignal=INT
stopwaitsecs=3
stopasgroup=true
killasgroup=true
redirect_stderr=true
stdout_logfile={logs / f"{name}.log"}
environment=PYTHONUNBUFFERED="1"
"""


@pytest.fixture
def supervised(tmp_path: Path) -> Iterator[tuple[str, str, Path]]:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    sock = tmp_path / "supervisor.sock"
    py = sys.executable
    conf = tmp_path / "supervisord.conf"
    conf.write_text(
        f"""[unix_http_server]
file={sock}

[supervisord]
logfile={tmp_path / "supervisord.log"}
pidfile={tmp_path / "supervisord.pid"}
nodaemon=true

[rpcinterface:supervisor]
supervisor.rpcinterface_factory = supervisor.rpcinterface:make_main_rpcinterface

"""
        + program("router", f"{py} -m services.router --listen {endpoint}", tmp_path)
        + program(
            "hang",
            f"{py} -m tests.integration.hang_service --hang-after-s {HANG_AFTER_S} --connect {endpoint}",
            tmp_path,
        )
        + program("crasher", f"{py} -c 'import time, sys; time.sleep({HANG_AFTER_S}); sys.exit(3)'", tmp_path)
        + program(
            "watchdog",
            f"{py} -m services.watchdog --supervisor-url unix://{sock} --backoff-s {BACKOFF_S} "
            f"--connect {endpoint}",
            tmp_path,
        )
    )
    proc = subprocess.Popen(
        [str(Path(py).parent / "supervisord"), "-c", str(conf)], cwd=REPO_ROOT, start_new_session=True
    )
    try:
        yield f"unix://{sock}", endpoint, tmp_path
    finally:
        stop(proc, signal.SIGTERM, timeout_s=20)


def hang_events(logs: Path) -> list[dict]:
    path = logs / "hang.log"
    lines = path.read_text().splitlines() if path.exists() else []
    return [json.loads(line) for line in lines if line.startswith('{"event"')]


def test_a_stuck_service_is_restarted_and_a_crash_loop_held(supervised: tuple[str, str, Path]) -> None:
    url, endpoint, logs = supervised
    deadline = time.monotonic() + 30
    while True:
        try:
            proxy = supervisor_proxy(url)
            first = proxy.supervisor.getProcessInfo("hang")
            if first["statename"] == "RUNNING":
                break
        except OSError:
            pass
        assert time.monotonic() < deadline, "supervisord did not start the programs"
        time.sleep(0.2)
    # The stuck service: a new process within 5 s of the loop stopping (its log says when, exactly).
    while len(events := hang_events(logs)) < 3:
        assert time.monotonic() < deadline + 30, f"the stuck service was not restarted: {events}"
        time.sleep(0.1)
    assert [e["event"] for e in events[:3]] == ["start", "hanging", "start"]
    restart_s = events[2]["t"] - events[1]["t"]
    print(f"stuck service restarted {restart_s:.2f} s after its loop stopped")
    assert restart_s <= RESTART_WITHIN_S
    # The crash loop: held (not running) for the backoff, reported meanwhile, then started again.
    conf = zenoh_config(DEFAULT_CLIENT_CONFIG, connect=[endpoint])
    with open_session(conf, timeout_s=10) as session:
        while (held := proxy.supervisor.getProcessInfo("crasher"))["statename"] != "STOPPED":
            assert time.monotonic() < deadline + 60, "the crash loop was not held"
            time.sleep(0.1)
        held_at = time.monotonic()
        time.sleep(1.0)
        reports, _ = query_health(session, timeout_s=2.0)
        (watchdog,) = [r for r in reports if r.service == "watchdog"]
        assert watchdog.level == HealthLevel.HEALTH_LEVEL_DEGRADED and "crasher" in watchdog.message
        while (again := proxy.supervisor.getProcessInfo("crasher"))["start"] == held["start"]:
            assert time.monotonic() < held_at + BACKOFF_S + 5, "the crash loop was never started again"
            time.sleep(0.1)
    gap_s = again["start"] - held["start"]  # from its last start before the hold to the next
    print(
        f"crash loop: no start for {gap_s:.1f} s (backoff {BACKOFF_S} s); watchdog said: {watchdog.message}"
    )
    assert gap_s >= BACKOFF_S


def test_the_router_killed_again_and_again_is_never_held(supervised: tuple[str, str, Path]) -> None:
    """Issue 34: the router SIGKILLed three times within seconds (a crash loop by count) is restarted
    each time and never stopped for a backoff: every other process depends on it."""
    url, _, logs = supervised
    deadline = time.monotonic() + 30

    def info_of(name: str) -> dict:
        return supervisor_proxy(url).supervisor.getProcessInfo(name)  # a fresh connection each time

    def router() -> dict:
        return info_of("router")

    def running_again(after_pid: int) -> dict:
        while (info := router())["statename"] != "RUNNING" or info["pid"] == after_pid:
            assert info["statename"] != "STOPPED", f"the router was held: {info}"
            assert time.monotonic() < deadline, f"the router did not come back: {info}"
            time.sleep(0.1)
        return info

    while True:
        try:
            info = router()
            if info["statename"] == "RUNNING" and info_of("watchdog")["statename"] == "RUNNING":
                break
        except OSError:
            pass
        assert time.monotonic() < deadline, "supervisord did not start the programs"
        time.sleep(0.2)
    time.sleep(2.0)  # the watchdog has looked at least once
    for _ in range(4):
        supervisor_proxy(url).supervisor.signalProcess("router", "KILL")
        info = running_again(info["pid"])
        deadline = time.monotonic() + 30
        time.sleep(1.5)
    time.sleep(2.0)  # a hold would have come at the third start
    assert router()["statename"] == "RUNNING"
    log_text = (logs / "watchdog.log").read_text()
    assert "hold router" not in log_text, log_text[-2000:]


def test_a_forged_health_reply_does_not_get_the_router_killed(supervised: tuple[str, str, Path]) -> None:
    """Issue 34, item 1: any process that reaches the router answers health queries on the router's own
    health key (nothing binds a key to its owner on one host), claiming the router's pid with a loop
    stalled for 999 s. The router answers for itself too: the watchdog sees two replies for one pid,
    judges neither, and the router keeps running."""
    from rmmdet.v1.health_pb2 import ServiceHealth

    from shared.bus.codec import encode
    from shared.bus.streams import get_stream

    url, endpoint, logs = supervised
    deadline = time.monotonic() + 30

    def info_of(name: str) -> dict:
        return supervisor_proxy(url).supervisor.getProcessInfo(name)

    while True:
        try:
            if all(info_of(n)["statename"] == "RUNNING" for n in ("router", "watchdog")):
                break
        except OSError:
            pass
        assert time.monotonic() < deadline, "supervisord did not start the programs"
        time.sleep(0.2)
    router_pid = info_of("router")["pid"]
    forged = ServiceHealth(service="router", instance="main", pid=router_pid, loop_age_s=999.0)
    forged.header.stamp.GetCurrentTime()
    forged.header.source_id = "site/router/main"
    encoded = encode(forged)
    key = get_stream("health").key(scope="site", service="router", instance="main")
    conf = zenoh_config(DEFAULT_CLIENT_CONFIG, connect=[endpoint])
    with open_session(conf, timeout_s=10) as session:
        queryable = session.declare_queryable(
            key, lambda q: q.reply(key, encoded.payload, encoding=encoded.encoding)
        )
        try:
            time.sleep(4.0)  # 16 polls of the watchdog
            reports, errors = query_health(session, timeout_s=2.0)
            claims = [(r.service, r.pid) for r in reports]
            assert sum(r.pid == router_pid for r in reports) == 2, (claims, router_pid, errors)
        finally:
            queryable.undeclare()
    after = info_of("router")
    assert (after["statename"], after["pid"]) == ("RUNNING", router_pid), after
    log_text = (logs / "watchdog.log").read_text()
    assert "restart router" not in log_text and "disagree" in log_text, log_text[-2000:]

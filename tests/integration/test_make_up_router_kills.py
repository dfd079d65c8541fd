"""The router SIGKILLed again and again under `make up` (issue 34): the whole system as the README
starts it, the one process everything depends on killed 5 times, 15 s apart.

Asserted after each kill: supervisord has it running again (the watchdog never holds it), every
agent's object lists flow again within 3 s of its return, and `rmmdet health`'s verdict is OK within
5 s. Over all five: no route request given up or refused (a request unanswered across a restart is
asked again; `tests.bench.fault_bench --router-kills 20` runs the same with 20 kills as a benchmark).

Starts the system itself and stops it after; fails (does not skip) when the system is already up, since
its router would be the one killed. Time limits scale with RSP_TIME_SCALE (slow machines).
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from collections.abc import Iterator

import pytest
import zenoh

from shared.bus.session import open_session
from shared.bus.zenoh_config import DEFAULT_CLIENT_CONFIG, zenoh_config
from shared.paths import DEFAULT_SCENE, REPO_ROOT
from shared.scene.scene import Scene
from shared.supervision.verdict import probe
from tests.bench.fault_bench import AGENTS, Watch, router_kills
from tests.bench.system_bench import supervised_pids

pytestmark = [pytest.mark.integration, pytest.mark.fault, pytest.mark.timeout(480)]

SCALE = float(os.environ.get("RSP_TIME_SCALE", "1"))
KILLS = 5
KILL_EVERY_S = 15.0
OBJECTS_AGAIN_WITHIN_S = 3.0 * SCALE
HEALTH_OK_WITHIN_S = 5.0 * SCALE
STARTUP_S = 120.0 * SCALE  # `make up` to the first OK health verdict


@pytest.fixture
def system() -> Iterator[tuple[zenoh.Session, Watch, Scene]]:
    assert not supervised_pids(), "the system is already up (`make down` first): this test kills its router"
    subprocess.run(["make", "-C", str(REPO_ROOT), "up"], check=True, stdout=subprocess.DEVNULL)
    session = None
    try:
        session = open_session(zenoh_config(DEFAULT_CLIENT_CONFIG), timeout_s=10)
        watch, scene = Watch(), Scene.load(DEFAULT_SCENE)
        subs = watch.subscribe(session)
        deadline = time.monotonic() + STARTUP_S
        while not probe(session, scene, timeout_s=1.0).ok:
            assert time.monotonic() < deadline, f"`make up` not healthy within {STARTUP_S:.0f} s"
            time.sleep(1.0)
        yield session, watch, scene
        for s in subs:
            s.undeclare()
    finally:
        if session is not None:
            session.close()
        subprocess.run(["make", "-C", str(REPO_ROOT), "down"], stdout=subprocess.DEVNULL)


def test_the_router_killed_five_times_under_make_up_is_back_each_time(system) -> None:
    session, watch, scene = system
    result = router_kills(watch, session, KILLS, KILL_EVERY_S, scene, health_limit_s=HEALTH_OK_WITHIN_S)
    report = json.dumps(result, indent=1)
    for each in result["each"]:
        assert not each["held"], report
        for agent in AGENTS:
            again_s = each["objects_again_s"][agent]
            assert again_s is not None and again_s <= OBJECTS_AGAIN_WITHIN_S, report
        assert each["health_ok_after_s"] is not None, report  # None: not OK within HEALTH_OK_WITHIN_S
    requests = result["requests"]
    assert requests["plans/requested"] > 0, report  # the vehicles did ask across the kills
    assert requests["plans/given_up"] == 0, report
    assert not any(v for k, v in requests.items() if k.startswith("plans/error_")), report

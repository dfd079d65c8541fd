"""A public real city live (issue 53 item 3, first part): Bologna's Pasubio district as the world
(`services/city`: libsumo on the clock of record, the roadside agents' object lists from the fitted
perception model, the cars as plan clients over the bus) and the coordinator service planning on its
scene, over a router: route requests answered and taken as SUMO routes, acknowledged, buses left alone,
the roadside agents LIVE in the coordinator's maps."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import pytest

from shared.paths import REPO_ROOT
from tests.helpers import Router, spawn, stop

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]

SCENARIO = REPO_ROOT / "tests" / "fixtures" / "real" / "sumo_scenarios" / "bologna_pasubio" / "run.sumocfg"
WATCH_S = 60.0
SPEED = 2.0


def test_a_real_city_runs_live_over_the_bus(router: Router, tmp_path: Path) -> None:
    from services.city.main import prepare

    work = tmp_path / "city"
    work.mkdir()
    city = prepare(SCENARIO, work, coverage=0.5, seed=1, range_m=60.0)
    assert city["junctions"]
    coordinator = spawn(
        ["-m", "services.coordinator", "--scene", str(work / "scene.yaml"), "--settings",
         str(work / "coordinator.yaml"), "--report-interval-s", "10", *router.client_args()]
    )  # fmt: skip
    world = spawn(
        ["-m", "services.city", "run", "--work", str(work), "--speed", str(SPEED),
         "--report-interval-s", "10", *router.client_args()]
    )  # fmt: skip
    try:
        time.sleep(WATCH_S)
    finally:
        stop(world, timeout_s=20.0)
        stop(coordinator)
    world_log = world.stdout.read() if world.stdout else ""
    coordinator_log = coordinator.stdout.read() if coordinator.stdout else ""
    print(world_log[-3000:], coordinator_log[-2000:])
    stopped = re.search(r"city stopped at (\d+) s: (\{.*\})", world_log)
    assert stopped, world_log[-2000:]
    counts = json.loads(stopped.group(2))
    assert counts.get("plans/requested", 0) > 100
    assert counts.get("plans/replied", 0) >= 0.9 * counts["plans/requested"]
    assert counts.get("acks/accepted", 0) >= 0.9 * counts["plans/replied"]
    assert counts.get("kept/class_bus", 0) > 0 and not counts.get("kept/route_refused")
    assert not any(k.startswith("rejected/plan_") for k in counts), counts

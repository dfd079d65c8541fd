"""Real processes: router + sim service + sensor group services. Sensor streams arrive at their
configured rates stamped with ground-truth ticks; killing one sensor process leaves the sim and the
other sensors running, and a restarted group resumes."""

from __future__ import annotations

import signal
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest

from shared.bus.node import Node
from shared.paths import DEFAULT_SCENE
from shared.scene.scene import Scene
from tests.helpers import Router, spawn, stop

pytestmark = [pytest.mark.integration, pytest.mark.fault, pytest.mark.timeout(120)]

#: Groups under test: the cheap ones (lidar, radar) so the test does not load the CI machine.
LIDARS = "agent1-lidars"
RADARS = "agent2-radars"
WINDOW_S = 3.0
STARTUP_S = 30.0
RATE_FRACTION = 0.8  # received / configured rate that counts as "at its rate" on a loaded CI box


@dataclass
class Arrivals:
    """Receive times per key, filled by subscriber threads."""

    times: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    ticks: dict[str, list[int]] = field(default_factory=lambda: defaultdict(list))
    lock: threading.Lock = field(default_factory=threading.Lock)

    def count(self, prefix: str, since: float) -> int:
        with self.lock:
            return sum(sum(t >= since for t in ts) for k, ts in self.times.items() if k.startswith(prefix))

    def wait_for(self, prefix: str, timeout_s: float) -> None:
        start = time.monotonic()
        deadline = start + timeout_s
        while self.count(prefix, start) == 0:
            if time.monotonic() > deadline:
                raise AssertionError(f"nothing on {prefix} within {timeout_s} s")
            time.sleep(0.1)


@pytest.fixture
def running(router: Router) -> Iterator[tuple[Router, Arrivals, dict]]:
    procs = {
        "sim": spawn(["-m", "services.sim", *router.client_args(), "--speed", "1"]),
        LIDARS: spawn(["-m", "services.sensor", "--group", LIDARS, *router.client_args()]),
        RADARS: spawn(["-m", "services.sensor", "--group", RADARS, *router.client_args()]),
    }
    arrivals = Arrivals()
    done = threading.Event()
    try:
        with Node(router.client_config(), service="test", instance="sensors", scope="site") as node:
            subs = [
                node.subscribe_stream("ground_truth", maxsize=1000),
                node.subscribe_stream("point_cloud", maxsize=1000),
                node.subscribe_stream("radar_scan", maxsize=1000),
            ]

            def consume(sub) -> None:
                while not done.is_set():
                    item = sub.recv(timeout=0.1)
                    if item is not None:
                        with arrivals.lock:
                            arrivals.times[item.key].append(time.monotonic())
                            arrivals.ticks[item.key].append(item.header.tick)

            threads = [threading.Thread(target=consume, args=(s,), daemon=True) for s in subs]
            for t in threads:
                t.start()
            yield router, arrivals, procs
            done.set()
            for t in threads:
                t.join(2)
    finally:
        for p in procs.values():
            stop(p)


def rates(arrivals: Arrivals, since: float, until: float) -> dict[str, float]:
    with arrivals.lock:
        return {k: sum(since <= t < until for t in ts) / (until - since) for k, ts in arrivals.times.items()}


def test_sensor_streams_run_at_their_rates_and_survive_a_killed_group(running) -> None:
    router, arrivals, procs = running
    scene = Scene.load(DEFAULT_SCENE)
    lidar_keys = {
        f"rmmdet/v1/agent1/sensor/lidar/{s.id}": s.rate_hz for s in scene.sensors_of("agent1", "lidar")
    }
    radar_keys = {
        f"rmmdet/v1/agent2/sensor/radar/{s.id}": s.rate_hz for s in scene.sensors_of("agent2", "radar")
    }
    gt_key = "rmmdet/v1/sim/ground_truth"
    arrivals.wait_for("rmmdet/v1/agent1/sensor/lidar", STARTUP_S)
    arrivals.wait_for("rmmdet/v1/agent2/sensor/radar", STARTUP_S)
    time.sleep(1.0)  # past start-up transients

    t0 = time.monotonic()
    time.sleep(WINDOW_S)
    measured = rates(arrivals, t0, time.monotonic())
    for key, rate_hz in {**lidar_keys, **radar_keys}.items():
        assert measured.get(key, 0.0) >= RATE_FRACTION * rate_hz, (key, measured)
    # Every sensor frame carries the tick of the ground truth it was rendered from.
    with arrivals.lock:
        gt_ticks = set(arrivals.ticks[gt_key])
        for key in lidar_keys | radar_keys:
            assert set(arrivals.ticks[key]) <= gt_ticks

    # Kill the lidar group hard: the sim and the radars keep going, the lidars stop.
    procs[LIDARS].send_signal(signal.SIGKILL)
    procs[LIDARS].wait(5)
    time.sleep(0.5)
    t1 = time.monotonic()
    time.sleep(WINDOW_S)
    after = rates(arrivals, t1, time.monotonic())
    assert procs["sim"].poll() is None and procs[RADARS].poll() is None
    assert all(after.get(k, 0.0) == 0.0 for k in lidar_keys), after
    for key, rate_hz in radar_keys.items():
        assert after.get(key, 0.0) >= RATE_FRACTION * rate_hz, (key, after)
    # Ground truth goes out on every tick on which a sensor fires.
    gt_rate_hz = max(s.rate_hz for s in scene.sensors.values())
    assert after.get(gt_key, 0.0) >= RATE_FRACTION * gt_rate_hz, after

    # Restart it: lidar frames come back.
    procs[LIDARS] = spawn(["-m", "services.sensor", "--group", LIDARS, *router.client_args()])
    arrivals.wait_for("rmmdet/v1/agent1/sensor/lidar", STARTUP_S)
    stop(procs[LIDARS])

"""Input monitor rates, ages, gaps and levels with a fake clock; the service health report."""

from __future__ import annotations

import pytest
from rmmdet.v1.common_pb2 import Header
from rmmdet.v1.health_pb2 import HealthLevel

from shared.bus.codec import Counters
from shared.bus.health import (
    CRITICAL,
    DEGRADED,
    LOOP_STALLED_AFTER_S,
    NOMINAL,
    HealthTracker,
    InputMonitor,
    RateThresholds,
    worst,
)


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _feed(monitor: InputMonitor, clock: FakeClock, rate_hz: float, seconds: float, seq_start: int = 1) -> int:
    seq = seq_start
    for _ in range(int(rate_hz * seconds)):
        clock.t += 1.0 / rate_hz
        monitor.record(Header(source_id="s", seq=seq), 100)
        seq += 1
    return seq


def test_levels_follow_rate_and_age() -> None:
    clock = FakeClock()
    m = InputMonitor("k", expected_rate_hz=10.0, thresholds=RateThresholds(window_s=1.0), clock_s=clock)
    assert m.level() == CRITICAL  # never received
    seq = _feed(m, clock, 10.0, 2.0)
    assert m.rate_hz() == pytest.approx(10.0, abs=1.0)
    assert m.level() == NOMINAL
    _feed(m, clock, 5.0, 2.0, seq)
    assert m.level() == DEGRADED  # half rate
    clock.t += 0.31  # > 3 periods of 10 Hz without data
    assert m.level() == CRITICAL
    assert m.to_proto().age_s >= 0.31


def test_unmonitored_input_is_nominal() -> None:
    m = InputMonitor("k")
    assert m.level() == NOMINAL
    assert m.to_proto().age_s == -1.0


def test_sequence_gaps_restarts_and_duplicates() -> None:
    m = InputMonitor("k")
    for seq in (1, 2, 5, 6):  # 3 and 4 lost
        m.record(Header(source_id="a", seq=seq))
    m.record(Header(source_id="a", seq=6))  # duplicate
    m.record(Header(source_id="a", seq=1))  # source restarted: not a gap
    m.record(Header(source_id="a", seq=2))
    m.record(Header(source_id="b", seq=10))  # another source: first sight
    assert (m.gaps, m.out_of_order, m.received) == (2, 1, 8)


def test_report_combines_inputs_status_and_counters() -> None:
    counters = Counters()
    counters.inc("rejected/decode", 3)
    tracker = HealthTracker("mec", "agent1", counters, "1.0")
    clock = FakeClock()
    good = InputMonitor("cam", 10.0, RateThresholds(window_s=1.0), clock)
    _feed(good, clock, 10.0, 1.0)
    tracker.add_input(good)
    report = tracker.report()
    assert report.level == HealthLevel.HEALTH_LEVEL_NOMINAL
    assert [(c.name, c.value) for c in report.counters] == [("rejected/decode", 3)]
    tracker.set_status(lambda: (DEGRADED, "lidar missing"))
    report = tracker.report()
    assert report.level == HealthLevel.HEALTH_LEVEL_DEGRADED
    assert report.message.startswith("lidar missing")
    tracker.add_input(InputMonitor("dead", 10.0, clock_s=clock))
    assert tracker.report().level == HealthLevel.HEALTH_LEVEL_CRITICAL


def test_worst() -> None:
    assert worst(NOMINAL, DEGRADED, NOMINAL) == DEGRADED
    assert worst(DEGRADED, CRITICAL) == CRITICAL
    assert worst() == NOMINAL


def test_a_stalled_main_loop_is_critical(monkeypatch: pytest.MonkeyPatch) -> None:
    now = [100.0]
    monkeypatch.setattr("shared.bus.health.time.monotonic", lambda: now[0])
    tracker = HealthTracker("mec", "agent1", Counters())
    assert tracker.report().loop_age_s == -1.0 and tracker.report().level == NOMINAL  # no loop yet
    tracker.beat()
    now[0] += LOOP_STALLED_AFTER_S
    report = tracker.report()
    assert report.loop_age_s == LOOP_STALLED_AFTER_S and report.level == NOMINAL
    now[0] += 0.5
    report = tracker.report()
    assert report.level == CRITICAL and report.message.startswith("main loop stalled for 3.5 s")
    tracker.beat()
    assert tracker.report().level == NOMINAL

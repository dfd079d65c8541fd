"""Known-answer tests of the live sim's schedule (sim.realtime) on a fake wall clock."""

from __future__ import annotations

import pytest

from sim.realtime import Every, RealTimeSchedule


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_ticks_are_due_at_their_wall_time_and_speed() -> None:
    clock = FakeClock()
    schedule = RealTimeSchedule(speed=2.0, late_tolerance_s=0.25, rtf_window_s=2.0, clock=clock)
    assert schedule.delay_s(1.0) == pytest.approx(0.5)  # 1 sim s at speed 2: 0.5 wall s after start
    clock.t += 0.6
    assert schedule.delay_s(1.0) == 0.0  # 0.1 s late: within tolerance, no re-anchoring
    assert schedule.anchor_s == 100.0


def test_a_late_sim_moves_the_schedule_on_instead_of_sprinting() -> None:
    clock = FakeClock()
    schedule = RealTimeSchedule(speed=1.0, late_tolerance_s=0.25, rtf_window_s=2.0, clock=clock)
    clock.t += 2.0
    assert schedule.delay_s(1.0) == 0.0  # 1 s late
    assert schedule.anchor_s == pytest.approx(101.0)
    assert schedule.delay_s(1.5) == pytest.approx(0.5)  # the next tick keeps its spacing


def test_holding_moves_the_schedule_and_is_counted() -> None:
    clock = FakeClock()
    schedule = RealTimeSchedule(speed=1.0, late_tolerance_s=0.25, rtf_window_s=2.0, clock=clock)
    schedule.hold(0.3)
    schedule.hold(0.2)
    assert schedule.held_s == pytest.approx(0.5)
    assert schedule.delay_s(1.0) == pytest.approx(1.5)


def test_real_time_factor_over_full_windows() -> None:
    clock = FakeClock()
    schedule = RealTimeSchedule(speed=1.0, late_tolerance_s=0.25, rtf_window_s=2.0, clock=clock)
    clock.t += 1.0
    assert schedule.measure(0.9) == 0.0  # no full window yet
    clock.t += 1.0
    assert schedule.measure(1.9) == pytest.approx(0.95)
    clock.t += 2.0
    assert schedule.measure(3.9) == pytest.approx(1.0)


def test_every_fires_once_per_period() -> None:
    every = Every(0.5)
    assert [every.due(t) for t in (0.0, 0.2, 0.5, 0.6, 1.0, 1.01)] == [True, False, True, False, True, False]


def test_speed_zero_never_waits() -> None:
    clock = FakeClock()
    schedule = RealTimeSchedule(speed=0.0, late_tolerance_s=0.25, rtf_window_s=2.0, clock=clock)
    assert schedule.delay_s(1000.0) == 0.0 and schedule.anchor_s == 100.0
    with pytest.raises(ValueError):
        RealTimeSchedule(speed=-1.0, late_tolerance_s=0.25, rtf_window_s=2.0)

"""SimTime: the clock of record follows the sim, never runs far past a stopped sim, and falls back to
the wall clock when there is no sim (or it is gone)."""

from __future__ import annotations

import pytest

from shared.timebase import NS_PER_S, SimTime

S = NS_PER_S
T0 = 1_700_000_000 * S  # a wall-clock epoch


def test_without_a_sim_it_is_the_wall_clock() -> None:
    clock = SimTime()
    assert not clock.following
    assert clock.now_ns(T0) == T0
    assert clock.now_s(T0 + S // 2) == pytest.approx(T0 / S + 0.5)


def test_follows_the_sim_clock_not_the_wall_clock() -> None:
    clock = SimTime(max_extrapolation_s=0.1, lost_after_s=2.0)
    sim0 = T0 - 30 * S  # a sim that ran at 0.7x for a while is 30 s behind the wall clock
    clock.on_clock(sim0, speed=1.0, wall_ns=T0)
    assert clock.following
    assert clock.now_ns(T0) == sim0
    assert clock.now_ns(T0 + 50_000_000) == sim0 + 50_000_000  # runs on at the sim's speed ...


def test_runs_on_at_most_the_bound_past_a_stopped_sim() -> None:
    clock = SimTime(max_extrapolation_s=0.1, lost_after_s=2.0)
    clock.on_clock(T0, speed=1.0, wall_ns=T0)
    # ... but a sim held back by a slow consumer stops this clock within 0.1 s of sim time.
    assert clock.now_ns(T0 + S) == T0 + 100_000_000
    assert clock.now_ns(T0 + 1_900_000_000) == T0 + 100_000_000


def test_extrapolation_uses_the_target_speed() -> None:
    clock = SimTime(max_extrapolation_s=0.1, lost_after_s=2.0)
    clock.on_clock(T0, speed=2.0, wall_ns=T0)
    assert clock.now_ns(T0 + 20_000_000) == T0 + 40_000_000  # 20 ms of wall = 40 ms of sim at 2x
    assert clock.speed == 2.0  # a wait of 40 ms on this clock is a 20 ms wall timeout
    clock.on_clock(T0, speed=0.0, wall_ns=T0)  # as fast as possible: run on at 1x
    assert clock.now_ns(T0 + 20_000_000) == T0 + 20_000_000
    assert clock.speed == 1.0 and SimTime().speed == 1.0


def test_a_sim_silent_past_the_lost_time_lets_the_clock_run_on_the_wall() -> None:
    clock = SimTime(max_extrapolation_s=0.1, lost_after_s=2.0)
    clock.on_clock(T0, speed=1.0, wall_ns=T0)
    assert clock.sim_alive(T0 + S)
    assert not clock.sim_alive(T0 + 2 * S)
    # Gone: inputs must go missing as time passes, as with real sensors.
    assert clock.now_ns(T0 + 5 * S) == T0 + 5 * S


def test_a_new_sample_resets_the_run_on() -> None:
    clock = SimTime(max_extrapolation_s=0.1, lost_after_s=2.0)
    clock.on_clock(T0, speed=1.0, wall_ns=T0)
    clock.on_clock(T0 + 50_000_000, speed=1.0, wall_ns=T0 + 400_000_000)  # sim at 1/8 speed
    assert clock.now_ns(T0 + 400_000_000) == T0 + 50_000_000
    assert clock.now_ns(T0 + 450_000_000) == T0 + 100_000_000


def test_arrival_before_the_last_sample_maps_to_that_sample() -> None:
    clock = SimTime()
    clock.on_clock(T0, speed=1.0, wall_ns=T0)
    assert clock.now_ns(T0 - 10_000_000) == T0


def test_rejects_bad_parameters() -> None:
    with pytest.raises(ValueError):
        SimTime(max_extrapolation_s=-1)
    with pytest.raises(ValueError):
        SimTime(lost_after_s=0)


def test_tick_rate_is_learnt_from_the_clock_step() -> None:
    clock = SimTime()
    assert clock.tick_hz is None  # no sim: no ticks
    clock.on_clock(T0, speed=1.0, wall_ns=T0)
    assert clock.tick_hz is None  # a clock sample without its step names no rate
    clock.on_clock(T0, speed=1.0, wall_ns=T0, step_s=1.0 / 60.0)
    assert clock.tick_hz == 60.0  # exactly: tick arithmetic floors tick * rate / tick_hz

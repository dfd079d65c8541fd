"""Pacer: the sim is held while a live consumer lags more than the bound, never by a dead one."""

from __future__ import annotations

import pytest

from sim.pacing import MIN_TIMEOUT_S, NS_PER_S, Pacer, silence_after_s

MS = NS_PER_S // 1000
T0 = 1_700_000_000 * NS_PER_S


def test_nothing_holds_before_any_consumer_reported() -> None:
    assert Pacer(max_lag_s=0.25, timeout_s=1.0).holding(T0, now_s=0.0) is None


def test_holds_while_the_newest_output_lags_more_than_the_bound() -> None:
    pacer = Pacer(max_lag_s=0.25, timeout_s=1.0)
    pacer.on_progress("mec1", T0, now_s=10.0)
    assert pacer.holding(T0 + 250 * MS, now_s=10.1) is None  # exactly the bound: free
    assert pacer.holding(T0 + 251 * MS, now_s=10.1) == "mec1"
    pacer.on_progress("mec1", T0 + 100 * MS, now_s=10.2)  # the consumer caught up
    assert pacer.holding(T0 + 300 * MS, now_s=10.2) is None


def test_the_most_lagging_consumer_is_named() -> None:
    pacer = Pacer(max_lag_s=0.25, timeout_s=1.0)
    pacer.on_progress("mec1", T0, now_s=10.0)
    pacer.on_progress("mec2", T0 - 200 * MS, now_s=10.0)
    assert pacer.holding(T0 + 300 * MS, now_s=10.0) == "mec2"
    assert pacer.lags_s(T0 + 300 * MS, now_s=10.0) == pytest.approx({"mec1": 0.3, "mec2": 0.5})


def test_an_older_output_arriving_late_does_not_move_progress_back() -> None:
    pacer = Pacer(max_lag_s=0.25, timeout_s=1.0)
    pacer.on_progress("mec1", T0, now_s=10.0)
    pacer.on_progress("mec1", T0 - 500 * MS, now_s=10.0)
    assert pacer.holding(T0 + 200 * MS, now_s=10.0) is None


def test_a_silent_consumer_stops_holding_after_the_timeout() -> None:
    pacer = Pacer(max_lag_s=0.25, timeout_s=1.0)
    pacer.on_progress("mec1", T0, now_s=10.0)
    assert pacer.holding(T0 + NS_PER_S, now_s=10.9) == "mec1"
    assert pacer.holding(T0 + NS_PER_S, now_s=11.1) is None  # killed or hung: the world goes on
    assert pacer.lags_s(T0 + NS_PER_S, now_s=11.1) == {}


def test_rejects_bad_parameters() -> None:
    with pytest.raises(ValueError):
        Pacer(max_lag_s=0, timeout_s=1.0)
    with pytest.raises(ValueError):
        Pacer(max_lag_s=0.25, timeout_s=0)


def test_a_consumer_whose_process_is_gone_is_forgotten_at_once() -> None:
    pacer = Pacer(max_lag_s=0.25, timeout_s=1.0)
    pacer.on_progress("agent1/sensor/agent1-cameras", T0, now_s=10.0)
    assert pacer.holding(T0 + NS_PER_S, now_s=10.1) == "agent1/sensor/agent1-cameras"
    pacer.forget("agent1/sensor/agent1-cameras")
    assert pacer.holding(T0 + NS_PER_S, now_s=10.1) is None
    pacer.forget("never-heard")  # harmless


def test_a_consumer_with_a_slow_cadence_may_lag_by_its_own_period() -> None:
    # Cameras asked for every 5th frame publish every 0.5 s: just before their next frame they lag by
    # 0.5 s without being late; only a lag beyond period + bound holds the sim.
    pacer = Pacer(max_lag_s=0.1, timeout_s=1.0)
    pacer.on_progress("agent1/sensor/agent1-cameras", T0, now_s=10.0)
    pacer.on_progress("agent1/sensor/agent1-cameras", T0 + 500 * MS, now_s=10.5)
    assert pacer.holding(T0 + 1100 * MS, now_s=10.6) is None  # 0.6 s = period + bound
    assert pacer.holding(T0 + 1101 * MS, now_s=10.6) == "agent1/sensor/agent1-cameras"


def test_cameras_taking_turns_do_not_hold_the_tick_of_their_next_turn() -> None:
    # 4 cameras on every 10th frame of 10 Hz: outputs on 4 consecutive frames, then none for 6.
    pacer = Pacer(max_lag_s=0.1, timeout_s=1.0)
    group = "agent1/sensor/agent1-cameras"
    now = 10.0
    for cycle in range(3):
        for k in range(4):
            stamp = T0 + (cycle * 1000 + k * 100) * MS
            pacer.on_progress(group, stamp, now_s=now)
            now += 0.1
        last = T0 + (cycle * 1000 + 300) * MS
        if cycle == 0:
            continue  # the first round has not shown the long gap yet
        # The ticks up to the next turn (0.7 s later) and the bound beyond it never hold the sim ...
        for tick_ms in range(100, 801, 100):
            assert pacer.holding(last + tick_ms * MS, now_s=now) is None, (cycle, tick_ms)
        # ... a group that misses its turn by more than the bound does.
        assert pacer.holding(last + 801 * MS, now_s=now) == group


def test_a_long_gap_is_not_taken_for_a_cadence() -> None:
    pacer = Pacer(max_lag_s=0.1, timeout_s=1.0)
    pacer.on_progress("mec1", T0, now_s=10.0)
    pacer.on_progress("mec1", T0 + 30 * NS_PER_S, now_s=10.5)  # restarted after 30 s of sim time
    assert pacer.holding(T0 + 31_200 * MS, now_s=10.6) == "mec1"  # period capped at 1 s


def test_hold_waits_until_the_consumer_catches_up_and_counts_who_held() -> None:
    pacer = Pacer(max_lag_s=0.25, timeout_s=5.0)
    wall = [10.0]
    outputs = iter([T0, T0, T0 + 100 * MS])  # the MEC catches up on the third look

    def take_progress() -> None:
        pacer.on_progress("mec1", next(outputs), wall[0])

    def sleep(seconds: float) -> bool:
        wall[0] += seconds
        return False

    held = pacer.hold(T0 + 300 * MS, take_progress, sleep, poll_s=0.01, clock=lambda: wall[0])
    assert held == pytest.approx(0.02)  # two polls
    assert pacer.held_by == {"mec1": pytest.approx(0.02)} and pacer.paced_by == ""


def test_hold_stops_at_shutdown() -> None:
    pacer = Pacer(max_lag_s=0.25, timeout_s=5.0)
    pacer.on_progress("mec1", T0, 0.0)
    held = pacer.hold(T0 + 1000 * MS, lambda: None, lambda _s: True, poll_s=0.01, clock=lambda: 0.0)
    assert held == 0.0 and pacer.paced_by == ""


def test_a_frozen_fast_consumer_is_let_go_after_two_of_its_cadences() -> None:
    """A SIGSTOPped 10 Hz sensor group (alive to Zenoh, silent) holds the sim ~0.2 s, not timeout_s."""
    pacer = Pacer(max_lag_s=0.1, timeout_s=1.0)
    for k in range(10):  # 10 Hz, in step with the wall clock
        pacer.on_progress("agent1/sensor/agent1-lidars", T0 + k * 100 * MS, now_s=10.0 + k * 0.1)
    last_heard = 10.9
    tick = T0 + 1300 * MS  # 0.4 s of sim time after its last output
    assert pacer.holding(tick, now_s=last_heard + 0.2) == "agent1/sensor/agent1-lidars"
    assert pacer.holding(tick, now_s=last_heard + 0.21) is None


def test_a_thawed_consumer_holds_again_only_once_it_has_caught_up() -> None:
    """Thawed, a sensor group first publishes a stale tick left in its pipe; the ticks it needs to catch
    up come only from a sim that goes on, so it holds nothing until its output is within the bound."""
    pacer = Pacer(max_lag_s=0.1, timeout_s=1.0)
    lidars = "agent3/sensor/agent3-lidars"
    for k in range(10):
        pacer.on_progress(lidars, T0 + k * 100 * MS, now_s=10.0 + k * 0.1)
    tick = T0 + 16_000 * MS  # frozen for 15 s
    pacer.on_progress(lidars, T0 + 1000 * MS, now_s=25.0)  # the stale tick
    assert pacer.holding(tick, now_s=25.0) is None
    assert pacer.holding(tick, now_s=25.5) is None
    pacer.on_progress(lidars, tick - 100 * MS, now_s=25.6)  # caught up: in step again
    assert pacer.holding(tick, now_s=25.6) is None
    assert pacer.holding(tick + 300 * MS, now_s=25.7) == lidars  # and holds when it lags again
    # Its cadence is its reports' own, not the freeze: silent after 2 x 0.1 s, not after the timeout.
    assert pacer.holding(tick + 300 * MS, now_s=25.6 + 0.21) is None


def test_a_slow_consumer_keeps_holding_for_its_own_cadence() -> None:
    """A consumer that is slow because the host is slow (one output per 0.4 s wall) is not silent."""
    pacer = Pacer(max_lag_s=0.1, timeout_s=1.0)
    for k in range(5):
        pacer.on_progress("mec1", T0 + k * 100 * MS, now_s=10.0 + k * 0.4)
    assert pacer.holding(T0 + 800 * MS, now_s=11.6 + 0.79) == "mec1"
    assert pacer.holding(T0 + 800 * MS, now_s=11.6 + 0.81) is None  # 2 x 0.4 s


def test_silence_is_two_wall_cadences_within_the_floor_and_the_timeout() -> None:
    assert silence_after_s([0.1, 0.12, 0.1], timeout_s=1.0) == pytest.approx(0.24)  # 2 x longest gap
    assert silence_after_s([0.02, 0.03], timeout_s=1.0) == MIN_TIMEOUT_S  # never sooner than the floor
    assert silence_after_s([0.9], timeout_s=1.0) == 1.0  # never later than the timeout
    assert silence_after_s([], timeout_s=1.0) == 1.0  # cadence unknown: the timeout


def test_a_consumer_reporting_without_catching_up_is_let_go_after_the_timeout() -> None:
    """Issue 34 item 4: a consumer that advances its stamps 1 ns per report (never silent, always
    lagging) holds the sim for at most `timeout_s`, then is let go (counted) until it is back within
    the bound, like a silent one."""
    pacer = Pacer(max_lag_s=0.1, timeout_s=1.0)
    tick = T0 + 1000 * MS
    stamp = T0
    for k in range(11):  # 1.0 s of reports, 10 a second, each 1 ns newer
        stamp += 1
        pacer.on_progress("rogue", stamp, now_s=10.0 + k * 0.1)
        assert pacer.holding(tick, now_s=10.0 + k * 0.1) == "rogue"
    stamp += 1
    pacer.on_progress("rogue", stamp, now_s=11.05)
    assert pacer.holding(tick, now_s=11.05) is None and pacer.let_go == {"rogue": 1}
    pacer.on_progress("rogue", tick - 50 * MS, now_s=11.1)  # back within the bound: holds again
    assert pacer.holding(tick, now_s=11.1) is None
    assert pacer.holding(tick + 300 * MS, now_s=11.2) == "rogue"


def test_a_consumer_catching_up_within_the_timeout_keeps_holding() -> None:
    """A genuine slow consumer that comes back within the bound restarts its lag clock: it is not let
    go for lagging again later."""
    pacer = Pacer(max_lag_s=0.1, timeout_s=1.0)
    for k in range(5):  # 10 Hz
        pacer.on_progress("mec1", T0 + k * 100 * MS, now_s=10.0 + k * 0.1)
    last = T0 + 400 * MS
    assert pacer.holding(last + 300 * MS, now_s=10.5) == "mec1"
    pacer.on_progress("mec1", last + 100 * MS, now_s=11.2)  # within the bound at last (0.7 s later)
    assert pacer.holding(last + 300 * MS, now_s=11.2) is None
    assert pacer.holding(last + 500 * MS, now_s=11.3) == "mec1"
    pacer.on_progress("mec1", last + 150 * MS, now_s=11.4)  # still lagging, still reporting
    pacer.on_progress("mec1", last + 180 * MS, now_s=11.55)
    # 1.1 s after it first lagged, but only 0.3 s after it lagged again: still held for, not let go
    assert pacer.holding(last + 500 * MS, now_s=11.6) == "mec1" and pacer.let_go == {}

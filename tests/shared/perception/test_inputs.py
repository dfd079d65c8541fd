"""Input health (OK / STALE / MISSING) and the FULL / DEGRADED hysteresis."""

from __future__ import annotations

import pytest

from shared.perception.inputs import InputState, SensorMonitor, Status, StatusHysteresis
from shared.timebase import NS_PER_S


def monitor(max_age_s: float = 0.2) -> SensorMonitor:
    return SensorMonitor(
        {"cam": 15.0, "lidar": 15.0}, missing_after_periods=3, max_age_s=max_age_s, start_s=0.0
    )


def test_missing_after_three_periods_without_frames() -> None:
    m = monitor()
    assert m.accept("cam", stamp_ns=10 * NS_PER_S, now_s=1.0, arrival_ns=10 * NS_PER_S)
    assert m.state("cam", 1.0 + 3 / 15) is InputState.OK
    assert m.state("cam", 1.0 + 3 / 15 + 1e-3) is InputState.MISSING
    # Never delivered: missing three periods after the monitor started.
    assert m.state("lidar", 0.19) is InputState.OK and m.state("lidar", 0.21) is InputState.MISSING
    assert m.alive(1.1) == ["cam"]


def test_old_frames_are_stale_dropped_and_counted() -> None:
    m = monitor()
    assert not m.accept(
        "cam", stamp_ns=10 * NS_PER_S, now_s=1.0, arrival_ns=10 * NS_PER_S + int(0.25 * NS_PER_S)
    )
    assert m.counts("cam") == (0, 1)
    assert m.state("cam", 1.0) is InputState.STALE
    assert m.accept("cam", stamp_ns=11 * NS_PER_S, now_s=1.1, arrival_ns=11 * NS_PER_S + int(0.05 * NS_PER_S))
    assert m.state("cam", 1.1) is InputState.OK
    (cam, _lidar) = m.report(1.2)
    assert cam.sensor_id == "cam" and cam.age_s == pytest.approx(0.1)


def test_staleness_check_can_be_turned_off_for_replays() -> None:
    m = monitor(max_age_s=0.0)
    assert m.accept("cam", stamp_ns=0, now_s=1.0, arrival_ns=100 * NS_PER_S)


def test_degraded_at_once_full_only_after_recover_frames() -> None:
    h = StatusHysteresis(recover_frames=3)
    assert h.update({"cam": True, "lidar": True}) is Status.FULL
    assert h.update({"cam": False, "lidar": True}) is Status.DEGRADED
    assert h.update({"cam": True, "lidar": True}) is Status.DEGRADED
    assert h.update({"cam": True, "lidar": True}) is Status.DEGRADED
    assert h.update({"cam": True, "lidar": True}) is Status.FULL
    assert h.transitions == 2


def test_stutter_does_not_flap_and_no_input_is_unavailable() -> None:
    h = StatusHysteresis(recover_frames=3)
    pattern = [False, True, True, False, True, True]  # a camera dropping every third frame
    states = [h.update({"cam": ok, "lidar": True}) for ok in pattern]
    assert states[1:] == [Status.DEGRADED] * 5 and h.transitions == 1
    assert h.update({"cam": False, "lidar": False}) is Status.UNAVAILABLE


def test_an_input_asked_for_fewer_frames_is_judged_at_its_new_rate() -> None:
    m = monitor()
    m.accept("cam", stamp_ns=10 * NS_PER_S, now_s=1.0, arrival_ns=10 * NS_PER_S)
    m.set_rate("cam", 3.0, now_s=1.05)  # every 5th frame of 15 Hz
    assert m.state("cam", 1.0 + 0.9) is InputState.OK  # 3 periods of 1/3 s
    assert m.state("cam", 1.0 + 1.01) is InputState.MISSING
    with pytest.raises(ValueError):
        m.set_rate("cam", 0.0, now_s=2.0)


def test_an_input_asked_for_more_frames_is_judged_at_its_new_rate_from_the_change() -> None:
    """A camera at every 10th frame (1 Hz) asked for every frame (10 Hz) 0.8 s after its last frame
    is not missing at once: it gets 3 new periods from the change. One already missing stays so."""
    m = SensorMonitor({"cam": 1.0, "lidar": 10.0}, missing_after_periods=3, max_age_s=0.5, start_s=0.0)
    m.accept("cam", stamp_ns=10 * NS_PER_S, now_s=1.0, arrival_ns=10 * NS_PER_S)
    m.set_rate("cam", 10.0, now_s=1.8)
    assert m.state("cam", 1.8 + 0.29) is InputState.OK
    assert m.state("cam", 1.8 + 0.31) is InputState.MISSING
    m.set_rate("cam", 1.0, now_s=3.0)  # back to 1 Hz: judged from its last frame (1.0) on
    assert m.state("cam", 3.9) is InputState.OK and m.state("cam", 4.01) is InputState.MISSING
    m.set_rate("cam", 10.0, now_s=5.0)  # missing when asked for more: no new grace
    assert m.state("cam", 5.01) is InputState.MISSING


def test_an_input_whose_process_is_gone_is_missing_at_once_until_it_delivers() -> None:
    m = monitor()
    m.accept("cam", stamp_ns=10 * NS_PER_S, now_s=1.0, arrival_ns=10 * NS_PER_S)
    m.mark_gone("cam")
    assert m.state("cam", 1.01) is InputState.MISSING and m.alive(1.01) == []
    m.accept("cam", stamp_ns=11 * NS_PER_S, now_s=2.0, arrival_ns=11 * NS_PER_S)  # restarted
    assert m.state("cam", 2.01) is InputState.OK

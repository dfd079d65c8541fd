"""Tick-exact join and bounded-wait collector: ordering, completion, timeouts, never stalling."""

from __future__ import annotations

import pytest

from shared.perception.sync import BoundedWaitCollector, Sample, TickJoiner

SENSORS = ("cam", "lidar", "radar")
MS = 1_000_000  # ns


def s(sensor: str, tick: int, stamp_ms: int | None = None) -> Sample:
    return Sample(sensor, (tick * 67 if stamp_ms is None else stamp_ms) * MS, f"{sensor}@{tick}", tick)


def test_tick_is_ready_when_every_expected_sensor_delivered() -> None:
    j = TickJoiner(SENSORS, max_wait_s=0.05)
    assert j.add(s("cam", 4), SENSORS, 0.0) == []
    assert j.add(s("lidar", 4), SENSORS, 0.001) == []
    (frame,) = j.add(s("radar", 4), SENSORS, 0.002)
    assert frame.tick == 4 and set(frame.samples) == set(SENSORS) and frame.missing == ()
    assert frame.samples["cam"].data == "cam@4" and frame.stamp_ns == 4 * 67 * MS


def test_dead_sensor_is_not_waited_for_and_is_reported_missing() -> None:
    j = TickJoiner(SENSORS, max_wait_s=0.05)
    alive = ("cam", "lidar")  # the monitor says radar is gone
    j.add(s("cam", 8), alive, 0.0)
    (frame,) = j.add(s("lidar", 8), alive, 0.001)
    assert frame.missing == () and set(frame.samples) == {"cam", "lidar"}


def test_timeout_emits_partial_frame_naming_the_missing_sensor() -> None:
    j = TickJoiner(SENSORS, max_wait_s=0.05)
    j.add(s("cam", 4), SENSORS, 1.0)
    j.add(s("lidar", 4), SENSORS, 1.01)
    assert j.poll(SENSORS, 1.049) == []
    assert j.next_deadline_s() == pytest.approx(1.05)
    (frame,) = j.poll(SENSORS, 1.05)
    assert frame.missing == ("radar",)
    # The radar's late sample of an emitted tick is dropped and counted, never joined.
    assert j.add(s("radar", 4), SENSORS, 1.06) == [] and j.late == 1
    assert j.late_by_sensor == {"radar": 1}


def test_a_clock_that_stands_still_holds_the_wait() -> None:
    # The MEC times the join on sim time: while a paced sim is held, an input late only because the
    # host is busy is still waited for; once the sim moves past the wait, the frame goes without it.
    j = TickJoiner(SENSORS, max_wait_s=0.1)
    j.add(s("lidar", 4), SENSORS, 50.0)
    assert j.poll(SENSORS, 50.099) == []  # sim time stopped just short of the bound (wall time ran on)
    (frame,) = j.add(s("cam", 4), SENSORS, 50.099) + j.poll(SENSORS, 50.1)
    assert frame.missing == ("radar",)


def test_newer_complete_tick_flushes_older_ticks_in_order() -> None:
    j = TickJoiner(SENSORS, max_wait_s=1.0)
    j.add(s("cam", 4), SENSORS, 0.0)
    for sensor in SENSORS:
        out = j.add(s(sensor, 8), SENSORS, 0.01)
    assert [f.tick for f in out] == [4, 8]
    assert out[0].missing == ("lidar", "radar") and out[1].missing == ()


def test_pending_ticks_are_bounded() -> None:
    j = TickJoiner(SENSORS, max_wait_s=10.0, max_pending=2)
    assert j.add(s("cam", 1), SENSORS, 0.0) == []
    assert j.add(s("cam", 2), SENSORS, 0.0) == []
    (out,) = j.add(s("cam", 3), SENSORS, 0.0)
    assert out.tick == 1


def test_duplicates_and_unknown_sensors_are_counted() -> None:
    j = TickJoiner(SENSORS, max_wait_s=1.0)
    j.add(s("cam", 1), SENSORS, 0.0)
    j.add(s("cam", 1), SENSORS, 0.0)
    j.add(s("sonar", 1), SENSORS, 0.0)
    assert (j.duplicates, j.unknown) == (1, 1)


def test_collector_joins_nearest_stamp_within_tolerance() -> None:
    c = BoundedWaitCollector("lidar", {"cam": 0.05, "radar": 0.05}, tolerance_s=0.04)
    c.add(s("cam", 0, stamp_ms=990), 0.0)
    c.add(s("cam", 0, stamp_ms=1020), 0.0)
    c.add(s("radar", 0, stamp_ms=950), 0.0)
    # cam already has a sample after the trigger stamp; radar may still deliver a nearer one: wait.
    assert c.add(s("lidar", 0, stamp_ms=1000), 0.0) == []
    (frame,) = c.add(s("radar", 0, stamp_ms=1003), 0.001)
    assert frame.samples["cam"].stamp_ns == 990 * MS and frame.samples["radar"].stamp_ns == 1003 * MS
    assert frame.missing == ()


def test_collector_waits_at_most_the_sensor_timeout() -> None:
    c = BoundedWaitCollector("lidar", {"cam": 0.03, "radar": 0.1}, tolerance_s=0.02)
    c.add(s("radar", 0, stamp_ms=1001), 0.0)
    c.add(s("radar", 0, stamp_ms=1060), 0.0)
    assert c.add(s("lidar", 0, stamp_ms=1000), 5.0) == []
    assert c.poll(5.029) == []
    (frame,) = c.poll(5.03)
    assert frame.missing == ("cam",) and "radar" in frame.samples


def test_collector_newer_trigger_releases_older_frame() -> None:
    c = BoundedWaitCollector("lidar", {"cam": 10.0}, tolerance_s=0.02)
    c.add(s("lidar", 0, stamp_ms=1000), 0.0)
    out = c.add(s("lidar", 0, stamp_ms=1100), 0.1)
    assert [f.stamp_ns for f in out] == [1000 * MS] and out[0].missing == ("cam",)


def test_invalid_settings_are_rejected() -> None:
    with pytest.raises(ValueError):
        TickJoiner(SENSORS, max_wait_s=0)
    with pytest.raises(ValueError):
        BoundedWaitCollector("lidar", {"lidar": 0.1}, tolerance_s=0.1)


def test_expected_sensors_may_depend_on_the_tick() -> None:
    # The camera is due on even ticks only (a capture demand): odd ticks do not wait for it.
    j = TickJoiner(SENSORS, max_wait_s=0.05)

    def expected(tick: int) -> set[str]:
        return set(SENSORS) if tick % 2 == 0 else {"lidar", "radar"}

    j.add(s("lidar", 3), expected, 0.0)
    (frame,) = j.add(s("radar", 3), expected, 0.001)
    assert frame.tick == 3 and frame.missing == ()
    j.add(s("lidar", 4), expected, 0.1)
    assert j.add(s("radar", 4), expected, 0.101) == []  # waits for the camera on tick 4
    (frame,) = j.poll(expected, 0.16)
    assert frame.missing == ("cam",)

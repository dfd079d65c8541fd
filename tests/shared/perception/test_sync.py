"""Tick-exact join and bounded-wait collector: ordering, completion, timeouts, never stalling."""

from __future__ import annotations

from dataclasses import replace

import pytest

from shared.perception.sync import BoundedWaitCollector, Sample, TickJoiner
from shared.scene.cadence import fires

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
    assert j.next_deadline_s(SENSORS) == pytest.approx(1.05)
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


# --- learnt waits and coasted frame ticks (a frozen sensor, docs/reliability.md F3) -------------------------
TICK_HZ = 60.0
FRAME_HZ = 10.0  # sensors fire every 6th tick


def frame_sample(sensor: str, frame: int) -> Sample:
    """A sensor frame of frame index `frame` (tick 6 * frame), stamped on its tick."""
    tick = frame * 6
    return Sample(sensor, round(tick * 1e9 / TICK_HZ), f"{sensor}@{tick}", tick)


def learnt_joiner(lateness_s: float = 0.04, frames: int = 12) -> TickJoiner:
    """A joiner that saw `frames` frames of cam + lidar, each arriving `lateness_s` after its stamp."""
    j = TickJoiner(
        ("cam", "lidar"),
        max_wait_s=0.2,
        min_wait_s=0.03,
        wait_factor=2.0,
        frame_tick=lambda tick, tick_hz: fires(FRAME_HZ, tick, tick_hz),
    )
    for f in range(frames):
        now = f / FRAME_HZ + lateness_s
        j.add(frame_sample("cam", f), ("cam", "lidar"), now)
        assert j.add(frame_sample("lidar", f), ("cam", "lidar"), now)
    return j


def test_the_wait_is_learnt_from_the_sensors_lateness() -> None:
    j = learnt_joiner(lateness_s=0.04)
    assert j.wait_s({"lidar"}) == pytest.approx(0.08)  # 2 x 40 ms
    f = 12
    j.add(frame_sample("cam", f), ("cam", "lidar"), f / FRAME_HZ + 0.04)
    assert j.poll(("cam", "lidar"), f / FRAME_HZ + 0.079, TICK_HZ) == []
    (frame,) = j.poll(("cam", "lidar"), f / FRAME_HZ + 0.08, TICK_HZ)  # not max_wait_s (0.2) later
    assert frame.missing == ("lidar",) and not frame.coasted
    # The lidar's frame comes later than that: dropped, counted, and the next waits are longer.
    assert j.add(frame_sample("lidar", f), ("cam", "lidar"), f / FRAME_HZ + 0.09) == [] and j.late == 1
    assert j.wait_s({"lidar"}) == pytest.approx(0.18)


def test_learnt_wait_is_bounded_and_needs_a_history() -> None:
    assert learnt_joiner(frames=3).wait_s({"lidar"}) is None  # too few arrivals: max_wait_s applies
    assert learnt_joiner(lateness_s=0.001).wait_s({"lidar"}) == pytest.approx(0.03)  # min_wait_s
    j = learnt_joiner(lateness_s=0.5)  # all late: still never more than max_wait_s after a first sample
    j.add(frame_sample("cam", 12), ("cam", "lidar"), 1.2)
    assert j.next_deadline_s(("cam", "lidar"), TICK_HZ) == pytest.approx(1.4)


def test_a_frame_tick_nobody_delivered_is_coasted_once_due() -> None:
    j = learnt_joiner(lateness_s=0.04)  # last emitted: frame 11 (tick 66)
    only_lidar = ("lidar",)  # e.g. the camera is not due on these frames
    assert j.poll(only_lidar, 1.2 + 0.079, TICK_HZ) == []
    assert j.next_deadline_s(only_lidar, TICK_HZ) == pytest.approx(1.28)
    (frame,) = j.poll(only_lidar, 1.2 + 0.08, TICK_HZ)
    assert frame.coasted and frame.tick == 72 and frame.samples == {} and frame.missing == ("lidar",)
    assert frame.stamp_ns == round(72 * 1e9 / TICK_HZ) and j.coasted == 1
    # Two frame ticks overdue at once: both, in order; the frozen lidar's frames, when they come, are late.
    frames = j.poll(only_lidar, 1.4 + 0.08, TICK_HZ)
    assert [f.tick for f in frames] == [78, 84]
    assert j.add(frame_sample("lidar", 12), only_lidar, 1.5) == [] and j.late == 1


def test_no_coasting_without_rates_or_expected_sensors() -> None:
    j = learnt_joiner()
    assert j.poll((), 5.0, TICK_HZ) == []  # nothing alive: nothing to say
    assert j.poll(("lidar",), 5.0, None) == []  # no sim tick rate known
    plain = TickJoiner(("cam", "lidar"), max_wait_s=0.2)  # no frame ticks given
    plain.add(frame_sample("cam", 0), ("cam",), 0.0)
    assert plain.poll(("lidar",), 5.0, TICK_HZ) == []


def test_a_pending_tick_is_waited_for_before_coasting_past_it() -> None:
    j = learnt_joiner(lateness_s=0.04)
    j.add(frame_sample("cam", 13), ("cam", "lidar"), 1.3 + 0.04)  # frame 12 nobody delivered, 13 pending
    frames = j.poll(("cam", "lidar"), 1.3 + 0.06, TICK_HZ)
    assert [f.tick for f in frames] == [72]  # frame 12 coasted, frame 13 still waits for its lidar
    assert frames[0].coasted


def test_add_never_times_out_a_tick_the_caller_may_still_hold_samples_of() -> None:
    """A busy MEC drains its queue after a long step: the deadlines are judged after every add."""
    j = learnt_joiner(lateness_s=0.04)
    both = ("cam", "lidar")
    j.add(frame_sample("cam", 12), both, 1.2 + 0.04)
    late_loop_s = 1.2 + 0.3  # the loop comes back long after the tick's deadline (1.28)
    assert j.add(frame_sample("cam", 13), both, late_loop_s) == []  # no timeout judged here
    (frame,) = j.add(replace(frame_sample("lidar", 12), arrival_s=1.2 + 0.05), both, late_loop_s)
    assert frame.tick == 72 and frame.missing == ()  # the lidar had arrived in time
    assert j.spread.latest_s("lidar") == pytest.approx(0.05)  # lateness from its arrival, not the loop

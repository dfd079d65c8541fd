"""Replay pacing with a fake clock: known send times at 1x, 2x and as fast as possible."""

from __future__ import annotations

import math

import pytest

from shared.recording.record import Record
from shared.recording.schedule import AS_FAST_AS_POSSIBLE, ReplayStats, replay, schedule

#: Recorded receive times relative to the first record, seconds.
OFFSETS_S = (0.0, 0.1, 0.1, 0.3, 1.0)
LOG0_NS = 1_700_000_000_000_000_000
START_S = 100.0


class FakeClock:
    """Monotonic seconds that only move when `wait` sleeps (or a test advances them)."""

    def __init__(self, start_s: float = START_S) -> None:
        self.now_s = start_s
        self.waits: list[float] = []

    def __call__(self) -> float:
        return self.now_s

    def wait(self, seconds: float) -> bool:
        self.waits.append(seconds)
        self.now_s += seconds
        return False


def recording(offsets_s: tuple[float, ...] = OFFSETS_S) -> list[Record]:
    return [
        Record(f"k/{i}", "application/protobuf;rmmdet.v1.SimClock", b"", None, LOG0_NS + round(t * 1e9), 0)
        for i, t in enumerate(offsets_s)
    ]


@pytest.mark.parametrize(
    ("speed", "expected_s"),
    [
        (1.0, [0.0, 0.1, 0.1, 0.3, 1.0]),
        (2.0, [0.0, 0.05, 0.05, 0.15, 0.5]),
        (0.5, [0.0, 0.2, 0.2, 0.6, 2.0]),
    ],
)
def test_schedule_known_answers(speed: float, expected_s: list[float]) -> None:
    clock = FakeClock()
    due = [t - START_S for _, t in schedule(recording(), speed, clock)]
    assert due == pytest.approx(expected_s)


@pytest.mark.parametrize("speed", [AS_FAST_AS_POSSIBLE, math.inf])
def test_schedule_as_fast_as_possible_is_now(speed: float) -> None:
    clock = FakeClock()
    assert [t for _, t in schedule(recording(), speed, clock)] == [START_S] * len(OFFSETS_S)


def test_schedule_anchors_when_the_first_record_is_pulled() -> None:
    clock = FakeClock()
    it = schedule(recording(), 1.0, clock)
    clock.now_s += 5.0  # e.g. opening the file took a while
    assert next(it)[1] == START_S + 5.0


@pytest.mark.parametrize(
    ("speed", "sent_s", "achieved"),
    [
        (1.0, [0.0, 0.1, 0.1, 0.3, 1.0], 1.0),
        (2.0, [0.0, 0.05, 0.05, 0.15, 0.5], 2.0),
        (AS_FAST_AS_POSSIBLE, [0.0] * 5, None),
    ],
)
def test_replay_sends_at_the_scheduled_times(
    speed: float, sent_s: list[float], achieved: float | None
) -> None:
    clock = FakeClock()
    sent: list[tuple[str, float]] = []
    stats = replay(
        recording(),
        lambda r: sent.append((r.key, clock() - START_S)),
        speed=speed,
        clock=clock,
        wait=clock.wait,
    )
    assert [k for k, _ in sent] == [f"k/{i}" for i in range(len(OFFSETS_S))]
    assert [t for _, t in sent] == pytest.approx(sent_s)
    assert stats.messages == len(OFFSETS_S)
    assert stats.recorded_s == pytest.approx(1.0)
    assert stats.wall_s == pytest.approx(sent_s[-1])
    if achieved is None:
        assert stats.achieved_speed is None
    else:
        assert stats.achieved_speed == pytest.approx(achieved)
    assert not stats.stopped


def test_slow_send_does_not_accumulate_drift() -> None:
    clock = FakeClock()
    sent: list[float] = []

    def slow_send(_record: Record) -> None:
        sent.append(clock() - START_S)
        clock.now_s += 0.08  # each send takes 80 ms

    replay(recording(), slow_send, speed=1.0, clock=clock, wait=clock.wait)
    # record 2 (due 0.1) goes at 0.1; record 3 (also due 0.1) is late and goes at once (0.18)
    assert sent == pytest.approx([0.0, 0.1, 0.18, 0.3, 1.0])


def test_stop_interrupts_and_loops_accumulate() -> None:
    clock = FakeClock()
    sent: list[str] = []

    def wait_then_stop(seconds: float) -> bool:
        clock.wait(seconds)
        return len(sent) >= 3

    stats = replay(recording(), lambda r: sent.append(r.key), speed=1.0, clock=clock, wait=wait_then_stop)
    assert stats.stopped
    assert sent == ["k/0", "k/1", "k/2"]  # k/2 needed no wait (same log time as k/1)

    clock = FakeClock()
    total = ReplayStats()
    for _ in range(2):
        replay(recording(), lambda r: None, speed=2.0, clock=clock, wait=clock.wait, stats=total)
    assert (total.passes, total.messages) == (2, 2 * len(OFFSETS_S))
    assert total.recorded_s == pytest.approx(2.0)
    assert total.achieved_speed == pytest.approx(2.0)


@pytest.mark.parametrize("speed", [-1.0, math.nan])
def test_invalid_speed_is_refused(speed: float) -> None:
    with pytest.raises(ValueError, match="speed"):
        list(schedule(recording(), speed, FakeClock()))

"""Replay timing: when to send each record, from log-time deltas and a speed factor (no Zenoh).

`speed` 1.0 = real time, N = N times faster, 0 or inf = as fast as possible. Send times are seconds on
the given clock (`time.monotonic` by default), anchored when the first record is pulled: record i is
due at `t0 + (log_time_i - log_time_0) / speed`. Times are absolute, so slow sends never accumulate
drift; a record that is already late is sent at once.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

from shared.recording.record import Record
from shared.timebase import NS_PER_S

#: `speed` value meaning "no pacing".
AS_FAST_AS_POSSIBLE = 0.0
Clock = Callable[[], float]  # seconds, monotonic
Wait = Callable[[float], bool]  # sleep up to the given seconds; True = stop requested


def is_as_fast_as_possible(speed: float) -> bool:
    return speed == AS_FAST_AS_POSSIBLE or math.isinf(speed)


def check_speed(speed: float) -> float:
    if math.isnan(speed) or speed < 0:
        raise ValueError(f"speed must be >= 0 (0 or inf = as fast as possible), got {speed}")
    return speed


def schedule(records: Iterable[Record], speed: float, clock: Clock) -> Iterator[tuple[Record, float]]:
    """(record, clock time to send it at) for every record, in input order."""
    check_speed(speed)
    fastest = is_as_fast_as_possible(speed)
    t0_s: float | None = None
    log0_ns = 0
    for record in records:
        if fastest:
            yield record, clock()
            continue
        if t0_s is None:
            t0_s, log0_ns = clock(), record.log_time_ns
        yield record, t0_s + max(0, record.log_time_ns - log0_ns) / NS_PER_S / speed


@dataclass
class ReplayStats:
    """Totals over one or more replay passes (times in seconds)."""

    messages: int = 0
    passes: int = 0
    recorded_s: float = 0.0  # log-time span replayed, summed over passes
    wall_s: float = 0.0  # clock time from first to last send, summed over passes
    stopped: bool = False  # interrupted by the wait function (shutdown)

    @property
    def achieved_speed(self) -> float | None:
        """Recorded span / wall time; None when either is zero (one message, or no pacing)."""
        if self.recorded_s <= 0 or self.wall_s <= 0:
            return None
        return self.recorded_s / self.wall_s


def _default_wait(stop: threading.Event | None) -> Wait:
    event = stop if stop is not None else threading.Event()
    return event.wait


def replay(
    records: Iterable[Record],
    send: Callable[[Record], None],
    *,
    speed: float = 1.0,
    clock: Clock,
    wait: Wait | None = None,
    stop: threading.Event | None = None,
    stats: ReplayStats | None = None,
) -> ReplayStats:
    """Call `send(record)` for every record at its scheduled time (one pass).

    `wait(seconds)` sleeps and returns True to stop early (default: `stop.wait`). Pass the same
    `stats` to several calls (`--loop`) to accumulate totals."""
    stats = stats if stats is not None else ReplayStats()
    wait = wait if wait is not None else _default_wait(stop)
    first_log_ns: int | None = None
    last_log_ns = 0
    first_send_s: float | None = None
    last_send_s = 0.0
    stats.passes += 1
    for record, due_s in schedule(records, speed, clock):
        delay_s = due_s - clock()
        if (delay_s > 0 and wait(delay_s)) or (stop is not None and stop.is_set()):
            stats.stopped = True
            break
        send(record)
        sent_s = clock()
        if first_log_ns is None:
            first_log_ns, first_send_s = record.log_time_ns, sent_s
        last_log_ns, last_send_s = record.log_time_ns, sent_s
        stats.messages += 1
    if first_log_ns is not None and first_send_s is not None:
        stats.recorded_s += max(0, last_log_ns - first_log_ns) / NS_PER_S
        stats.wall_s += last_send_s - first_send_s
    return stats

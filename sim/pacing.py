"""Pacing: the sim never runs more than a bounded lag ahead of its slowest consumer. No bus inside.

A live sim on a host that cannot keep up would otherwise outrun the loop: sensors skip ticks, the MECs
judge their inputs stale and the coordinator its agents. Instead the sim holds a tick back while a
consumer's newest output (its stamp: the sim time of the data it was made from) lags the tick by more
than its own output period (the longest interval between its last `PERIOD_WINDOW` outputs, each at
most `MAX_PERIOD_S`) plus `max_lag_s` of sim time, so the whole loop slows down together and stays
correct; the real-time factor it reaches is reported. Counting the period in lets a consumer with a
slow or uneven cadence run at it without holding the sim: a lidar agent's cameras taking turns on
every 10th frame publish on 4 consecutive frames, then on none for 6 (gaps 0.1, 0.1, 0.1, 0.7 s),
and must not hold the tick of their next turn; a 10 Hz consumer's lag stays bounded to 0.2 s.

A consumer whose process is gone (`forget`, on its liveliness token vanishing) or that is silent (hung,
or stopped: a SIGSTOPped process keeps its token until the router's lease runs out) no longer holds the
sim: a killed, hung or frozen MEC or sensor service must not stop the world. Silent means no report for
`SILENCE_PERIODS` of the consumer's own wall cadence (the longest wall gap between its recent reports,
so a consumer that is slow because the host is slow keeps holding), at least `MIN_TIMEOUT_S` and at most
`timeout_s`: a frozen 10 Hz sensor group holds the sim for ~0.2 s, not 1 s. A silent consumer that
reports again holds again once its output is back within the bound, not before: a thawed sensor group
first works off the stale ticks left in its pipe, and the ticks it needs to catch up with are the ones
the sim would not publish while held by it (it held the whole loop for a further `timeout_s` that way).
A consumer that keeps reporting but stays beyond the bound for `timeout_s` (wall) is let go the same
way (`let_go`): otherwise one advancing its stamps 1 ns at a time would hold the world for ever (issue
34, item 4). Before its first report a consumer holds nothing (models still loading). Times: sim
stamps in ns, wall times in monotonic seconds.
"""

from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from shared.timebase import NS_PER_S

MAX_PERIOD_S = 1.0  # a gap longer than this (a restarted consumer) is not its cadence
PERIOD_WINDOW = 8  # outputs whose gaps make up a consumer's period: one full round of cameras taking turns
SILENCE_PERIODS = 2.0  # wall cadences without a report after which a consumer is silent
MIN_TIMEOUT_S = 0.15  # ... but never sooner (wall s): one late frame of a 10 Hz consumer is not silence


def silence_after_s(wall_gaps_s: Iterable[float], timeout_s: float) -> float:
    """Wall seconds without a report after which a consumer with these recent wall gaps between its
    reports is silent: SILENCE_PERIODS of its cadence (the longest gap), within [MIN_TIMEOUT_S,
    `timeout_s`]; `timeout_s` while its cadence is unknown."""
    cadence_s = max(wall_gaps_s, default=timeout_s)
    return min(timeout_s, max(MIN_TIMEOUT_S, SILENCE_PERIODS * cadence_s))


@dataclass
class _Consumer:
    stamp_ns: int
    heard_s: float
    gaps_ns: deque[int] = field(default_factory=lambda: deque(maxlen=PERIOD_WINDOW))
    wall_gaps_s: deque[float] = field(default_factory=lambda: deque(maxlen=PERIOD_WINDOW))
    rejoining: bool = False  # reported after a silence, not yet back within the lag bound
    lagging_since_s: float | None = None  # wall time its lag first went beyond the bound (None: within)

    @property
    def period_ns(self) -> int:
        """Longest recent gap between two outputs, sim ns (0 until known)."""
        return max(self.gaps_ns, default=0)

    def silent(self, now_s: float, timeout_s: float) -> bool:
        """No report for `silence_after_s` of its recent wall cadence."""
        return now_s - self.heard_s > silence_after_s(self.wall_gaps_s, timeout_s)


class Pacer:
    """Which consumer (if any) holds the sim back.

    Parameters
    ----------
    max_lag_s : float
        Largest lag of a consumer's newest output behind the tick about to be published beyond the
        consumer's own output period, s of sim time.
    timeout_s : float
        Longest wall time without a report after which a consumer no longer holds the sim, s (a consumer
        with a short cadence is let go sooner, see the module doc).
    """

    def __init__(self, max_lag_s: float, timeout_s: float) -> None:
        if max_lag_s <= 0 or timeout_s <= 0:
            raise ValueError("max_lag_s and timeout_s must be > 0")
        self.max_lag_ns = round(max_lag_s * NS_PER_S)
        self.max_period_ns = round(MAX_PERIOD_S * NS_PER_S)
        self.timeout_s = timeout_s
        self._consumers: dict[str, _Consumer] = {}
        self.paced_by = ""  # the consumer holding the sim right now ("" when none)
        self.held_by: Counter[str] = Counter()  # wall seconds each consumer held the sim, in all
        self.let_go: Counter[str] = Counter()  # times a consumer lagging for timeout_s was let go

    def on_progress(self, consumer: str, stamp_ns: int, now_s: float) -> None:
        """`consumer` published an output made from data stamped `stamp_ns` (reordered ones count too:
        only the newest stamp is kept)."""
        c = self._consumers.get(consumer)
        if c is None:
            self._consumers[consumer] = _Consumer(stamp_ns, now_s)
        else:
            if stamp_ns > c.stamp_ns:
                if c.silent(now_s, self.timeout_s):
                    c.rejoining = True
                elif not c.rejoining:  # a silence and the catching up after it are not its cadence
                    c.gaps_ns.append(min(stamp_ns - c.stamp_ns, self.max_period_ns))
                    # Wall cadence of new outputs (several outputs of one burst, e.g. a group's sensors
                    # of one tick, are one report).
                    c.wall_gaps_s.append(min(now_s - c.heard_s, self.timeout_s))
                c.stamp_ns = stamp_ns
                c.heard_s = now_s

    def forget(self, consumer: str) -> None:
        """`consumer` is gone (its liveliness token vanished): it holds nothing until it reports again."""
        self._consumers.pop(consumer, None)

    def holding(self, tick_stamp_ns: int, now_s: float) -> str | None:
        """The most lagging live consumer if publishing `tick_stamp_ns` would exceed the lag bound (a
        rejoining consumer found back within it holds from now on)."""
        worst: tuple[int, str] | None = None
        for name, c in self._consumers.items():
            if c.silent(now_s, self.timeout_s):
                continue
            lag = tick_stamp_ns - c.stamp_ns - c.period_ns
            if c.rejoining:
                if lag > self.max_lag_ns:
                    continue
                c.rejoining = False
            if lag <= self.max_lag_ns:
                c.lagging_since_s = None
                continue
            if c.lagging_since_s is None:
                c.lagging_since_s = now_s
            elif now_s - c.lagging_since_s > self.timeout_s:
                # Reporting, but not catching up for `timeout_s`: let go like a silent one (it holds
                # again once back within the bound). A consumer advancing its stamps by 1 ns a report
                # would otherwise hold the world for ever.
                c.rejoining, c.lagging_since_s = True, None
                self.let_go[name] += 1
                continue
            if worst is None or lag > worst[0]:
                worst = (lag, name)
        return None if worst is None else worst[1]

    def lags_s(self, tick_stamp_ns: int, now_s: float) -> dict[str, float]:
        """Lag of every live consumer behind `tick_stamp_ns`, s of sim time."""
        return {
            name: (tick_stamp_ns - c.stamp_ns) / NS_PER_S
            for name, c in self._consumers.items()
            if not c.silent(now_s, self.timeout_s)
        }

    def hold(
        self,
        tick_stamp_ns: int,
        take_progress: Callable[[], None],
        sleep: Callable[[float], bool],
        poll_s: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> float:
        """Wait while a consumer lags more than allowed; returns the wall seconds held.

        ``take_progress()`` feeds the consumers' newest outputs (`on_progress`, `forget`) before each
        look; ``sleep(poll_s)`` waits between looks and returns True to stop waiting (shutdown).
        """
        start = clock()
        take_progress()
        while (lagging := self.holding(tick_stamp_ns, clock())) is not None:
            self.paced_by = lagging
            t = clock()
            if sleep(poll_s):
                break
            self.held_by[lagging] += clock() - t
            take_progress()
        self.paced_by = ""
        return clock() - start

"""The live sim's wall-clock schedule: when a tick of sim time is due, and the real-time factor reached.

Sim time is the clock of record; `RealTimeSchedule` maps it to wall time at ``speed`` sim seconds per
wall second through an anchor (the monotonic wall time of sim time 0). The anchor moves on whenever the
sim is held by lagging consumers (`sim.pacing.Pacer`) or falls behind by more than ``late_tolerance_s``,
so the sim resumes at its speed instead of sprinting to catch up. Times in seconds; the wall clock is
injectable for tests.
"""

from __future__ import annotations

import time
from collections.abc import Callable


class RealTimeSchedule:
    """Wall-clock pacing of sim time at ``speed`` (0: as fast as possible, never waits), with the
    real-time factor measured over ``rtf_window_s`` of wall time."""

    def __init__(
        self,
        speed: float,
        late_tolerance_s: float,
        rtf_window_s: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if speed < 0:
            raise ValueError("speed must be >= 0")
        self.speed = speed
        self.late_tolerance_s = late_tolerance_s
        self.rtf_window_s = rtf_window_s
        self._clock = clock
        self.anchor_s = clock()  # wall time of sim time 0
        self.held_s = 0.0  # wall seconds held by consumers in all
        self.rtf = 0.0  # real-time factor over the latest full window (0 until one has passed)
        self._rtf_mark = (self.anchor_s, 0.0)  # (wall, sim) at the start of the window

    def delay_s(self, sim_time_s: float) -> float:
        """Wall seconds to wait before publishing sim time ``sim_time_s`` (0 when due). Later than
        ``late_tolerance_s``: the schedule moves on (the host cannot keep up; slow down, do not sprint)."""
        if self.speed == 0:
            return 0.0
        wait = self.anchor_s + sim_time_s / self.speed - self._clock()
        if wait < -self.late_tolerance_s:
            self.anchor_s -= wait
            return 0.0
        return max(wait, 0.0)

    def hold(self, held_s: float) -> None:
        """The sim was held ``held_s`` wall seconds: the schedule moves on by as much."""
        self.anchor_s += held_s
        self.held_s += held_s

    def measure(self, sim_time_s: float) -> float:
        """The real-time factor, re-measured when a window has passed since the last measurement."""
        now = self._clock()
        wall0, sim0 = self._rtf_mark
        if now - wall0 >= self.rtf_window_s:
            self.rtf = (sim_time_s - sim0) / (now - wall0)
            self._rtf_mark = (now, sim_time_s)
        return self.rtf


class Every:
    """A cadence on sim time: `due` is True once per ``period_s`` (the first time at ``start_s``)."""

    def __init__(self, period_s: float, start_s: float = 0.0) -> None:
        if period_s <= 0:
            raise ValueError("period_s must be > 0")
        self.period_s = period_s
        self.next_s = start_s

    def due(self, t_s: float) -> bool:
        if t_s < self.next_s:
            return False
        self.next_s += self.period_s
        return True

"""The clock of record: simulated time when a sim runs (ROS `use_sim_time`), else the wall clock.

Freshness, staleness, input-health and coverage timeouts are judged on this clock, so a host that
cannot keep real time (or a sim run faster than 1x) slows the whole loop consistently instead of
marking every input stale. Stamps on the bus are already sim time (the sim stamps ground truth with
its start wall time + simulated seconds, and every derived message inherits the stamp).

`SimTime` follows the sim's `SimClock` samples. Between samples it runs on at the sim's target speed
for at most `max_extrapolation_s` of sim time: a sim that stops (paced by a slow consumer, or busy)
stops this clock within that bound, so nothing looks older than it is. A sim that stays silent for
`lost_after_s` of wall time is gone: the clock then runs freely on the wall clock from its last sample,
so inputs go missing and agents stale as they would with real sensors. Before any sample it is the
wall clock (real sensors, no sim). All times in ns since the UNIX epoch unless named `_s`.
"""

from __future__ import annotations

import threading
import time

NS_PER_S = 1_000_000_000
MAX_STAMP_NS = 2**63 - 1  # a stamp is int64 ns since the UNIX epoch (a header's, a recording's)
MAX_SIM_SPEED = 100.0  # sim seconds per wall second a sim may run at (and a SimClock may claim)
TICK_HZ_DECIMALS = 6


def tick_stamp_ns(epoch_ns: int, tick: int, tick_hz: float) -> int:
    """Stamp of tick `tick` of the sim run whose tick 0 is stamped `epoch_ns` (`Header.epoch`), ns."""
    return epoch_ns + round(tick * NS_PER_S / tick_hz)


class SimTime:
    """Thread-safe sim-time follower.

    Parameters
    ----------
    max_extrapolation_s : float
        Longest run-on past the last clock sample while the sim is alive, s of sim time: one clock
        period (the sim publishes its clock at 20 Hz), so a held sim is never overrun by more.
    lost_after_s : float
        Wall seconds of silence after which the sim is taken as gone.
    """

    def __init__(self, max_extrapolation_s: float = 0.05, lost_after_s: float = 2.0) -> None:
        if max_extrapolation_s < 0 or lost_after_s <= 0:
            raise ValueError("max_extrapolation_s must be >= 0 and lost_after_s > 0")
        self.max_extrapolation_ns = round(max_extrapolation_s * NS_PER_S)
        self.lost_after_ns = round(lost_after_s * NS_PER_S)
        self._lock = threading.Lock()
        self._sim_ns: int | None = None  # last sample: sim time ...
        self._wall_ns = 0  # ... and the wall time it was heard
        self._speed = 1.0
        self._tick_hz: float | None = None
        self._epoch_ns: int | None = None
        self.samples = 0

    def on_clock(
        self, sim_ns: int, speed: float, wall_ns: int | None = None, step_s: float = 0.0, epoch_ns: int = 0
    ) -> None:
        """A SimClock sample: sim time `sim_ns`, the sim's target speed (sim s per wall s; 0, as fast
        as possible, runs on at 1x), its tick period `step_s` (0: unknown) and the stamp of its run's
        tick 0 `epoch_ns` (Header.epoch; 0: unknown). A restarted sim may move the clock back: its
        samples are taken as they come."""
        wall = time.time_ns() if wall_ns is None else wall_ns
        with self._lock:
            self._sim_ns = sim_ns
            self._wall_ns = wall
            self._speed = speed if speed > 0 else 1.0
            if step_s > 0:
                # Rounded: tick arithmetic (shared.scene.cadence) needs 60.0, not 59.99999999999999.
                self._tick_hz = round(1.0 / step_s, TICK_HZ_DECIMALS)
            if epoch_ns > 0:
                self._epoch_ns = epoch_ns
            self.samples += 1

    @property
    def tick_hz(self) -> float | None:
        """The sim's ticks per simulated second, once a clock sample named it (None: no sim, or unknown)."""
        with self._lock:
            return self._tick_hz

    @property
    def epoch_ns(self) -> int | None:
        """Stamp of the sim run's tick 0 (Header.epoch), once a clock sample named it."""
        with self._lock:
            return self._epoch_ns

    @property
    def speed(self) -> float:
        """Sim seconds per wall second the clock runs at (1.0 without a sim): converts a wait on this
        clock into a wall-clock timeout."""
        with self._lock:
            return self._speed

    @property
    def following(self) -> bool:
        """True once a sim clock has been heard (sim time is the clock of record)."""
        with self._lock:
            return self._sim_ns is not None

    def sim_alive(self, wall_ns: int | None = None) -> bool:
        wall = time.time_ns() if wall_ns is None else wall_ns
        with self._lock:
            return self._sim_ns is not None and wall - self._wall_ns < self.lost_after_ns

    def now_ns(self, wall_ns: int | None = None) -> int:
        """The clock of record at wall time `wall_ns` (default now)."""
        wall = time.time_ns() if wall_ns is None else wall_ns
        with self._lock:
            if self._sim_ns is None:
                return wall
            run_on = round(max(0, wall - self._wall_ns) * self._speed)
            if wall - self._wall_ns < self.lost_after_ns:
                run_on = min(run_on, self.max_extrapolation_ns)
            return self._sim_ns + run_on

    def now_s(self, wall_ns: int | None = None) -> float:
        return self.now_ns(wall_ns) / NS_PER_S

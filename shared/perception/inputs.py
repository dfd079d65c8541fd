"""Input health of one agent's sensors and the FULL / DEGRADED status of its output.

Health model (docs/reliability.md (b.1), after Autoware / ROS diagnostics): each input has an expected rate
f. It is MISSING when nothing arrived for `missing_after_periods / f` (3 periods: 300 ms at 10 Hz), so
a dead or frozen sensor is noticed well before a Zenoh liveliness lease (10 s) would say so. A frame
whose sensor stamp is older than `max_age_s` on arrival is STALE: dropped and counted, never fused;
the input is STALE while only stale frames arrive.

The output status is DEGRADED as soon as any configured input is not OK and returns to FULL only after
`recover_frames` consecutive output frames with every input OK (hysteresis: no flapping when a sensor
stutters); UNAVAILABLE when no input is OK.

Times are on the clock of record (shared/timebase.py: sim time when a sim runs, else the wall clock):
`now_s` in seconds, `arrival_ns` and stamps in UNIX-epoch ns. Staleness compares the sensor stamp with
the arrival time on that clock, so a sim slower than real time does not make its frames stale;
`max_age_s = 0` turns it off for replays and lock-step runs.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass

from shared.timebase import NS_PER_S


class InputState(enum.Enum):
    OK = "ok"
    STALE = "stale"
    MISSING = "missing"


class Status(enum.Enum):
    FULL = "full"
    DEGRADED = "degraded"
    UNAVAILABLE = "unavailable"


@dataclass
class _Input:
    rate_hz: float
    last_accepted_s: float | None = None
    last_stale_s: float | None = None
    accepted: int = 0
    stale: int = 0
    gone: bool = False  # its producing process left the bus: MISSING until it delivers again
    rate_since_s: float | None = None  # when it was last asked for more frames while OK


@dataclass(frozen=True)
class InputReport:
    sensor_id: str
    state: InputState
    age_s: float  # since the last accepted frame; -1 if never


class SensorMonitor:
    """Per-sensor arrival bookkeeping.

    Parameters
    ----------
    rates_hz : mapping of str to float
        Every configured input and its expected rate, Hz.
    missing_after_periods : float
        Periods without an accepted frame after which an input is MISSING.
    max_age_s : float
        Frames older than this on arrival (arrival time - sensor stamp) are stale; 0 disables the check.
    start_s : float
        Monotonic time the monitor starts; an input that never delivers is MISSING from
        `start_s + missing_after_periods / rate`.
    """

    def __init__(
        self,
        rates_hz: Mapping[str, float],
        missing_after_periods: float,
        max_age_s: float,
        start_s: float,
    ) -> None:
        if any(r <= 0 for r in rates_hz.values()) or missing_after_periods <= 0 or max_age_s < 0:
            raise ValueError("rates and missing_after_periods must be > 0, max_age_s >= 0")
        self._inputs = {s: _Input(r) for s, r in rates_hz.items()}
        self.missing_after_periods = missing_after_periods
        self.max_age_s = max_age_s
        self.start_s = start_s

    @property
    def sensors(self) -> list[str]:
        return list(self._inputs)

    def set_rate(self, sensor_id: str, rate_hz: float, now_s: float) -> None:
        """The rate `sensor_id` is expected at from `now_s` on (e.g. a camera asked for every n-th
        frame), Hz. An input OK at the change is judged on a higher rate from `now_s`, not from its last
        frame: a camera asked for every frame after 1 s at every 10th is not missing at once for frames
        it was not asked for. One already missing stays missing; a lower rate is judged from the last
        frame."""
        if rate_hz <= 0:
            raise ValueError(f"rate must be > 0, got {rate_hz}")
        inp = self._inputs[sensor_id]
        if rate_hz < inp.rate_hz:
            inp.rate_since_s = None
        elif rate_hz > inp.rate_hz and self.state(sensor_id, now_s) is InputState.OK:
            inp.rate_since_s = now_s
        inp.rate_hz = rate_hz

    def accept(self, sensor_id: str, stamp_ns: int, now_s: float, arrival_ns: int) -> bool:
        """Record an arrival; False (and counted as stale) when the frame is too old to fuse."""
        inp = self._inputs[sensor_id]
        if self.max_age_s > 0 and arrival_ns - stamp_ns > self.max_age_s * NS_PER_S:
            inp.stale += 1
            inp.last_stale_s = now_s
            return False
        inp.accepted += 1
        inp.last_accepted_s = now_s
        inp.gone = False
        return True

    def mark_gone(self, sensor_id: str) -> None:
        """The process producing `sensor_id` is gone (its presence token vanished): MISSING at once,
        not after `missing_after_periods`, until a frame of it is accepted again."""
        self._inputs[sensor_id].gone = True

    def state(self, sensor_id: str, now_s: float) -> InputState:
        inp = self._inputs[sensor_id]
        if inp.gone:
            return InputState.MISSING
        limit_s = self.missing_after_periods / inp.rate_hz
        last = inp.last_accepted_s if inp.last_accepted_s is not None else self.start_s
        if inp.rate_since_s is not None:
            last = max(last, inp.rate_since_s)
        if now_s - last <= limit_s:
            return InputState.OK
        if inp.last_stale_s is not None and now_s - inp.last_stale_s <= limit_s:
            return InputState.STALE
        return InputState.MISSING

    def alive(self, now_s: float) -> list[str]:
        """Inputs currently OK (the ones a joiner should wait for)."""
        return [s for s in self._inputs if self.state(s, now_s) is InputState.OK]

    def report(self, now_s: float) -> list[InputReport]:
        out = []
        for s, inp in self._inputs.items():
            age = -1.0 if inp.last_accepted_s is None else now_s - inp.last_accepted_s
            out.append(InputReport(s, self.state(s, now_s), age))
        return out

    def counts(self, sensor_id: str) -> tuple[int, int]:
        """(accepted, stale) frames of one input."""
        inp = self._inputs[sensor_id]
        return inp.accepted, inp.stale


class StatusHysteresis:
    """FULL / DEGRADED / UNAVAILABLE of the output, one update per output frame.

    Parameters
    ----------
    recover_frames : int
        Consecutive all-OK frames needed to go back to FULL.
    """

    def __init__(self, recover_frames: int) -> None:
        if recover_frames < 1:
            raise ValueError("recover_frames must be >= 1")
        self.recover_frames = recover_frames
        self.status = Status.FULL
        self._good = recover_frames  # start FULL: nothing has failed yet
        self.transitions = 0

    def update(self, fused_ok: Mapping[str, bool]) -> Status:
        """`fused_ok`: per configured input, whether it contributed a valid frame to this output."""
        ok = list(fused_ok.values())
        if ok and all(ok):
            self._good += 1
            new = Status.FULL if self._good >= self.recover_frames else self.status
        else:
            self._good = 0
            new = Status.DEGRADED if any(ok) else Status.UNAVAILABLE
        if new is not self.status:
            self.transitions += 1
            self.status = new
        return self.status

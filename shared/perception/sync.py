"""Input synchronisation of one agent's sensors: which frames are fused together, and when.

Two joiners, one contract: `add` a sensor sample, `poll` the clock, and take the `JoinedFrame`s that
are ready, oldest first. Neither ever waits unboundedly: a sensor that does not deliver is left out of
the frame (listed in `JoinedFrame.missing`) once its wait is over, so a dead sensor degrades the
output instead of stalling it.

`TickJoiner` (simulated sensors): every sensor of a sim tick carries that tick's id and stamp, so
frames are joined exactly on the tick. A tick is ready when every sensor that is currently expected
has delivered it, when its wait has passed since its first sample arrived, or when a newer tick is
ready (ticks are emitted in order). The wait is learnt (`ArrivalSpread`): a tick is due by its stamp
plus `wait_factor` times the latest that each awaited sensor arrived after its stamp over its recent
ticks (at least `min_wait_s`), and never waits more than `max_wait_s` after its first sample. A frozen
sensor (alive to the bus, sending nothing) then delays its agent's frames by about twice its usual
latency, not `max_wait_s`, until its health monitor declares it missing; a sensor later than the wait
is late (dropped, counted) and its lateness widens the next waits. Told which ticks are frame ticks
(`frame_tick`) and the sim's tick rate, the joiner also emits a frame with no samples for a frame tick
on which no expected sensor delivered by its deadline (`JoinedFrame.coasted`): a tick where only the
frozen sensor was due must not become a gap in the agent's output. Which sensors are expected is the
caller's choice per `poll`/`add` call, a set or a function of the tick (the MEC passes the inputs its
health monitor thinks alive, less the cameras not due on that tick, so neither a dead camera nor a
skipped frame is waited for).

`BoundedWaitCollector` (real, asynchronous sensors): a frame is triggered by each sample of the
`trigger` sensor; every other sensor contributes its sample nearest to the trigger stamp within
`tolerance_s`. The frame waits for a sensor at most that sensor's own timeout after the trigger
arrived, then goes out without it.

Times: `now_s` is any monotonic clock in seconds (the MEC passes the clock of record: sim time under a
sim, so a held sim holds the wait), stamps are sensor times in ns.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field
from typing import Any

from shared.bus.ordering import Order, Position, order
from shared.timebase import NS_PER_S

MAX_FRAME_TICKS = 10_000  # longest run of ticks searched for the next frame tick

#: The sensors a tick waits for: one set for every tick, or a function of the tick.
Expected = Collection[str] | Callable[[int], Collection[str]]


@dataclass(frozen=True)
class Sample:
    """One decoded sensor frame."""

    sensor_id: str
    stamp_ns: int
    data: Any
    tick: int = 0
    arrival_s: float = 0.0
    epoch: int = 0  # sim run of `tick` (Header.epoch)


@dataclass
class JoinedFrame:
    """The samples fused as one agent frame, and the expected sensors that did not deliver."""

    stamp_ns: int
    tick: int
    samples: dict[str, Sample]
    missing: tuple[str, ...] = ()
    first_arrival_s: float = 0.0
    coasted: bool = False  # no expected sensor delivered this frame tick by its deadline


class ArrivalSpread:
    """How late each sensor arrives after its stamp (on the join's clock), over its recent ticks.

    Parameters
    ----------
    window : int
        Arrivals remembered per sensor.
    min_samples : int
        Arrivals a sensor needs before its spread is trusted (until then it is waited for the most).
    """

    # 200 arrivals (20 s of a 10 Hz sensor): its max reaches the rare stalls of a busy host's sensor
    # services (a 50-arrival window left 0.3 % of lidar frames late under `make up`).
    def __init__(self, window: int = 200, min_samples: int = 10) -> None:
        if window < 1 or not 1 <= min_samples <= window:
            raise ValueError("window >= 1 and 1 <= min_samples <= window")
        self.min_samples = min_samples
        self._offsets_s: dict[str, deque[float]] = {}
        self._window = window

    def record(self, sensor_id: str, lateness_s: float) -> None:
        """A sample of `sensor_id` arrived `lateness_s` after its stamp."""
        self._offsets_s.setdefault(sensor_id, deque(maxlen=self._window)).append(max(0.0, lateness_s))

    def latest_s(self, sensor_id: str) -> float | None:
        """The latest recent arrival of `sensor_id` after its stamp, s (None: too few arrivals yet)."""
        offsets = self._offsets_s.get(sensor_id)
        if offsets is None or len(offsets) < self.min_samples:
            return None
        return max(offsets)


@dataclass
class _Pending:
    tick: int
    stamp_ns: int
    first_arrival_s: float
    samples: dict[str, Sample] = field(default_factory=dict)


class TickJoiner:
    """Exact join on the simulation tick, with a bounded wait per tick.

    Parameters
    ----------
    sensors : collection of str
        Every sensor this agent may fuse.
    max_wait_s : float
        Longest wait for the expected sensors of a tick after its first sample arrived, s.
    min_wait_s, wait_factor : float
        The learnt wait for a sensor after a tick's stamp: `wait_factor` x its latest recent arrival
        after its stamp, at least `min_wait_s` (s); `wait_factor` 0 waits `max_wait_s` always.
    frame_tick : callable, optional
        ``frame_tick(tick, tick_hz)``: True if some sensor captures on `tick`. With the sim's tick rate
        (`poll`), frame ticks no sensor delivered by their deadline are emitted empty (coasted). None:
        never.
    max_pending : int
        Ticks held at once; when exceeded the oldest is emitted as it is.
    reset_after_ticks : int
        A sample this many ticks behind the last emitted one, or of another sim run (epoch), restarts
        the join (shared/bus/ordering.py): a restarted sim or one bogus tick cannot latch it.
    """

    def __init__(
        self,
        sensors: Collection[str],
        max_wait_s: float,
        max_pending: int = 4,
        reset_after_ticks: int = 120,
        min_wait_s: float = 0.0,
        wait_factor: float = 0.0,
        frame_tick: Callable[[int, float], bool] | None = None,
    ) -> None:
        if max_wait_s <= 0 or max_pending < 1 or reset_after_ticks < 1:
            raise ValueError("max_wait_s must be > 0, max_pending and reset_after_ticks >= 1")
        if not 0 <= min_wait_s <= max_wait_s or wait_factor < 0:
            raise ValueError("0 <= min_wait_s <= max_wait_s and wait_factor >= 0")
        self.sensors = frozenset(sensors)
        self.max_wait_s = max_wait_s
        self.min_wait_s = min_wait_s
        self.wait_factor = wait_factor
        self.frame_tick = frame_tick
        self.spread = ArrivalSpread()
        self._last_emitted_ns = 0  # stamp of the last emitted tick
        self.coasted = 0  # frame ticks emitted empty
        self.max_pending = max_pending
        self.reset_after_ticks = reset_after_ticks
        self._pending: dict[int, _Pending] = {}
        self._last_emitted: Position | None = None
        self._epoch: int | None = None  # of the pending ticks
        self.restarts = 0
        self.late = 0  # samples of a tick already emitted (counted, dropped)
        self.late_by_sensor: Counter[str] = Counter()  # ... and whose they were
        self.duplicates = 0
        self.unknown = 0

    def add(self, sample: Sample, expected: Expected, now_s: float) -> list[JoinedFrame]:
        """Add one sample; returns the frames that became ready (oldest first)."""
        if sample.sensor_id not in self.sensors:
            self.unknown += 1
            return []
        newest = self._last_emitted
        if newest is None and self._epoch is not None:
            newest = Position(self._epoch, -1)
        verdict = order(newest, Position(sample.epoch, sample.tick), self.reset_after_ticks)
        if verdict is Order.OLDER:
            self.late += 1
            self.late_by_sensor[sample.sensor_id] += 1
            self.spread.record(sample.sensor_id, self._lateness_s(sample, now_s))
            return []
        if verdict is Order.RESTART:
            self.restarts += 1
            self._pending.clear()
            self._last_emitted = None
        self._epoch = sample.epoch
        pending = self._pending.get(sample.tick)
        if pending is None:
            pending = _Pending(sample.tick, sample.stamp_ns, now_s)
            self._pending[sample.tick] = pending
        if sample.sensor_id in pending.samples:
            self.duplicates += 1
            return []
        pending.samples[sample.sensor_id] = sample
        self.spread.record(sample.sensor_id, self._lateness_s(sample, now_s))
        # Only what this sample completed: timeouts are judged by `poll`, after the caller has added
        # every sample it already holds (a busy loop must not time out a tick whose samples it has).
        return self._take(expected, now_s, timeouts=False)

    @staticmethod
    def _lateness_s(sample: Sample, now_s: float) -> float:
        """How long after its stamp `sample` arrived (its `arrival_s` if set, else `now_s`)."""
        return (sample.arrival_s or now_s) - sample.stamp_ns / NS_PER_S

    def _wanted(self, expected: Expected, tick: int) -> frozenset[str]:
        return self.sensors.intersection(expected(tick) if callable(expected) else expected)

    def wait_s(self, awaited: Collection[str]) -> float | None:
        """How long after its stamp a tick waits for the `awaited` sensors, s (None: not learnt yet)."""
        if self.wait_factor == 0:
            return None
        wait = self.min_wait_s
        for sensor_id in awaited:
            latest = self.spread.latest_s(sensor_id)
            if latest is None:
                return None
            wait = max(wait, self.wait_factor * latest)
        return wait

    def _deadline_s(self, p: _Pending, expected: Expected) -> float:
        cap_s = p.first_arrival_s + self.max_wait_s
        learnt = self.wait_s(self._wanted(expected, p.tick).difference(p.samples))
        return cap_s if learnt is None else min(cap_s, p.stamp_ns / NS_PER_S + learnt)

    def _next_frame(self, tick_hz: float | None) -> tuple[int, int] | None:
        """The frame tick after the last emitted one and its stamp (None: unknown)."""
        if self._last_emitted is None or self.frame_tick is None or not tick_hz:
            return None
        last = self._last_emitted.value
        tick = next(
            (t for t in range(last + 1, last + 1 + MAX_FRAME_TICKS) if self.frame_tick(t, tick_hz)), None
        )
        if tick is None:
            return None
        return tick, self._last_emitted_ns + round((tick - self._last_emitted.value) * NS_PER_S / tick_hz)

    def _coast(self, expected: Expected, now_s: float, tick_hz: float | None) -> list[JoinedFrame]:
        """Empty frames for the frame ticks after the last emitted one that nothing arrived for."""
        out: list[JoinedFrame] = []
        while len(out) < self.max_pending and (nxt := self._next_frame(tick_hz)) is not None:
            tick, stamp_ns = nxt
            if any(t <= tick for t in self._pending):
                break
            awaited = self._wanted(expected, tick)
            learnt = self.wait_s(awaited)
            wait = self.max_wait_s if learnt is None else min(learnt, self.max_wait_s)
            if not awaited or now_s < stamp_ns / NS_PER_S + wait:
                break
            out.append(JoinedFrame(stamp_ns, tick, {}, tuple(sorted(awaited)), coasted=True))
            self._emitted(tick, stamp_ns)
            self.coasted += 1
        return out

    def _emitted(self, tick: int, stamp_ns: int) -> None:
        self._last_emitted = Position(self._epoch or 0, tick)
        self._last_emitted_ns = stamp_ns

    def poll(self, expected: Expected, now_s: float, tick_hz: float | None = None) -> list[JoinedFrame]:
        """Frames ready at `now_s`: complete, timed out, or older than a ready one, and the frame ticks
        coasted (given the sim's `tick_hz`); oldest first."""
        return self._take(expected, now_s, timeouts=True) + self._coast(expected, now_s, tick_hz)

    def _take(self, expected: Expected, now_s: float, timeouts: bool) -> list[JoinedFrame]:
        ready_tick = -1
        for tick, p in self._pending.items():
            complete = self._wanted(expected, tick).issubset(p.samples)
            if complete or (timeouts and now_s >= self._deadline_s(p, expected)):
                ready_tick = max(ready_tick, tick)
        overflow = len(self._pending) - self.max_pending
        ticks = sorted(self._pending)
        if overflow > 0:
            ready_tick = max(ready_tick, ticks[overflow - 1])
        out = []
        for tick in ticks:
            if tick > ready_tick:
                break
            p = self._pending.pop(tick)
            missing = tuple(sorted(self._wanted(expected, tick).difference(p.samples)))
            out.append(JoinedFrame(p.stamp_ns, tick, p.samples, missing, p.first_arrival_s))
            self._emitted(tick, p.stamp_ns)
        return out

    def next_deadline_s(self, expected: Expected, tick_hz: float | None = None) -> float | None:
        """Time (on the `now_s` clock) at which the first pending tick times out, or the next frame tick
        is coasted (None if neither)."""
        deadlines = [self._deadline_s(p, expected) for p in self._pending.values()]
        if (
            not self._pending
            and (nxt := self._next_frame(tick_hz)) is not None
            and (awaited := self._wanted(expected, nxt[0]))
        ):
            learnt = self.wait_s(awaited)
            deadlines.append(
                nxt[1] / NS_PER_S + (self.max_wait_s if learnt is None else min(learnt, self.max_wait_s))
            )
        return min(deadlines, default=None)


@dataclass
class _Trigger:
    sample: Sample
    arrival_s: float


class BoundedWaitCollector:
    """Frames triggered by one sensor; the others join by nearest stamp within a tolerance.

    Parameters
    ----------
    trigger : str
        Sensor whose samples start a frame (e.g. the lidar).
    timeouts_s : mapping of str to float
        Every other sensor and the longest it is waited for after a trigger arrived, s.
    tolerance_s : float
        Largest |stamp - trigger stamp| of a sample joined to a frame, s.
    history : int
        Samples kept per sensor to choose the nearest from.
    """

    def __init__(
        self, trigger: str, timeouts_s: Mapping[str, float], tolerance_s: float, history: int = 8
    ) -> None:
        if trigger in timeouts_s:
            raise ValueError("the trigger sensor has no timeout of its own")
        if tolerance_s <= 0 or any(t < 0 for t in timeouts_s.values()):
            raise ValueError("tolerance must be > 0 and timeouts >= 0")
        self.trigger = trigger
        self.timeouts_s = dict(timeouts_s)
        self.tolerance_ns = int(tolerance_s * NS_PER_S)
        self._history: dict[str, deque[Sample]] = {s: deque(maxlen=history) for s in timeouts_s}
        self._triggers: deque[_Trigger] = deque()
        self.unknown = 0

    def add(self, sample: Sample, now_s: float) -> list[JoinedFrame]:
        if sample.sensor_id == self.trigger:
            self._triggers.append(_Trigger(sample, now_s))
        elif sample.sensor_id in self._history:
            self._history[sample.sensor_id].append(sample)
        else:
            self.unknown += 1
            return []
        return self.poll(now_s)

    def poll(self, now_s: float) -> list[JoinedFrame]:
        out = []
        while self._triggers:
            trig = self._triggers[0]
            waiting = [
                s
                for s, timeout in self.timeouts_s.items()
                if not self._covered(s, trig.sample.stamp_ns) and now_s - trig.arrival_s < timeout
            ]
            # A newer trigger means the older frame can wait no longer (frames go out in order).
            if waiting and len(self._triggers) == 1:
                break
            self._triggers.popleft()
            out.append(self._frame(trig))
        return out

    def _covered(self, sensor_id: str, stamp_ns: int) -> bool:
        """True once the sensor has a sample at or after the trigger stamp (nothing nearer can come)."""
        return any(s.stamp_ns >= stamp_ns for s in self._history[sensor_id])

    def _frame(self, trig: _Trigger) -> JoinedFrame:
        stamp = trig.sample.stamp_ns
        samples = {self.trigger: trig.sample}
        missing = []
        for sensor_id, history in self._history.items():
            near = [s for s in history if abs(s.stamp_ns - stamp) <= self.tolerance_ns]
            if near:
                samples[sensor_id] = min(near, key=lambda s: abs(s.stamp_ns - stamp))
            else:
                missing.append(sensor_id)
        return JoinedFrame(stamp, trig.sample.tick, samples, tuple(sorted(missing)), trig.arrival_s)

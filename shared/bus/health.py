"""Receiving-side input monitoring and the service health report.

Liveliness says a process is connected, not that it works (docs/reliability.md (c).4), so degradation is
driven by data: each input has an expected rate; it is DEGRADED when its rate over the window falls
below `warn_rate_fraction` of that, and CRITICAL (missing) when nothing arrived for
`missing_after_periods` periods (the ROS diagnostic_updater / Autoware topic_state_monitor model).
"""

from __future__ import annotations

import os
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from rmmdet.v1.common_pb2 import Header
from rmmdet.v1.health_pb2 import Counter, HealthLevel, InputHealth, ServiceHealth

from shared.bus.codec import Counters

NOMINAL = HealthLevel.HEALTH_LEVEL_NOMINAL
DEGRADED = HealthLevel.HEALTH_LEVEL_DEGRADED
CRITICAL = HealthLevel.HEALTH_LEVEL_CRITICAL
UNKNOWN = HealthLevel.HEALTH_LEVEL_UNKNOWN

_SEVERITY = {NOMINAL: 0, UNKNOWN: 1, DEGRADED: 2, CRITICAL: 3}


def worst(*levels: HealthLevel.ValueType) -> HealthLevel.ValueType:
    return max(levels, key=_SEVERITY.__getitem__, default=NOMINAL)


@dataclass(frozen=True)
class RateThresholds:
    warn_rate_fraction: float = 0.9  # DEGRADED below this fraction of the expected rate
    missing_after_periods: float = 3.0  # CRITICAL after this many expected periods without data
    window_s: float = 2.0  # rate measured over this window


DEFAULT_THRESHOLDS = RateThresholds()


class InputMonitor:
    """Rate, age, sequence gaps and level of one subscribed input."""

    def __init__(
        self,
        key_expr: str,
        expected_rate_hz: float = 0.0,
        thresholds: RateThresholds = DEFAULT_THRESHOLDS,
        clock_s: Callable[[], float] = time.monotonic,
    ) -> None:
        self.key_expr = key_expr
        self.expected_rate_hz = expected_rate_hz
        self.thresholds = thresholds
        self._clock_s = clock_s
        self._lock = threading.Lock()
        self._arrivals_s: deque[float] = deque()
        self._last_seq: dict[str, int] = {}
        self.received = 0
        self.received_bytes = 0
        self.gaps = 0  # sequence numbers never seen
        self.out_of_order = 0  # duplicates or older than the last seen
        self.last_arrival_s: float | None = None

    def record(self, header: Header | None, size_bytes: int = 0) -> None:
        now = self._clock_s()
        with self._lock:
            self.received += 1
            self.received_bytes += size_bytes
            self.last_arrival_s = now
            self._arrivals_s.append(now)
            self._trim(now)
            if header is not None and header.seq:
                last = self._last_seq.get(header.source_id)
                if last is None or header.seq == 1:  # first sight, or the source restarted
                    pass
                elif header.seq > last + 1:
                    self.gaps += header.seq - last - 1
                elif header.seq <= last:
                    self.out_of_order += 1
                    return
                self._last_seq[header.source_id] = header.seq

    def _trim(self, now: float) -> None:
        horizon = now - self.thresholds.window_s
        while self._arrivals_s and self._arrivals_s[0] < horizon:
            self._arrivals_s.popleft()

    def rate_hz(self) -> float:
        with self._lock:
            self._trim(self._clock_s())
            return len(self._arrivals_s) / self.thresholds.window_s

    def age_s(self) -> float | None:
        with self._lock:
            return None if self.last_arrival_s is None else self._clock_s() - self.last_arrival_s

    def level(self) -> HealthLevel.ValueType:
        if self.expected_rate_hz <= 0:
            return NOMINAL
        age = self.age_s()
        if age is None or age > self.thresholds.missing_after_periods / self.expected_rate_hz:
            return CRITICAL
        if self.rate_hz() < self.thresholds.warn_rate_fraction * self.expected_rate_hz:
            return DEGRADED
        return NOMINAL

    def to_proto(self) -> InputHealth:
        age = self.age_s()
        return InputHealth(
            key_expr=self.key_expr,
            expected_rate_hz=self.expected_rate_hz,
            rate_hz=self.rate_hz(),
            age_s=-1.0 if age is None else age,
            received=self.received,
            gaps=self.gaps,
            level=self.level(),
        )


StatusFn = Callable[[], tuple["HealthLevel.ValueType", str]]
#: A main loop that has not gone round for this long is stalled: CRITICAL in its health, and the
#: watchdog (services/watchdog) restarts the process (its `--stall-after-s` defaults to this). Every
#: service loop wakes at least once a second, busy or idle.
LOOP_STALLED_AFTER_S = 3.0


class HealthTracker:
    """Assembles a ServiceHealth from input monitors, counters and a service-specific status."""

    def __init__(self, service: str, instance: str, counters: Counters, version: str = "") -> None:
        self.service = service
        self.instance = instance
        self.counters = counters
        self.version = version
        self.started_s = time.monotonic()
        self._beat_s: float | None = None  # monotonic time of the main loop's last round
        self._inputs: list[InputMonitor] = []
        self._status_fn: StatusFn | None = None
        self._lock = threading.Lock()

    def add_input(self, monitor: InputMonitor) -> None:
        with self._lock:
            self._inputs.append(monitor)

    def set_status(self, fn: StatusFn) -> None:
        """Service-specific level and message (e.g. a MEC's FULL/DEGRADED fusion state).

        `fn` runs inside the health queryable's Zenoh callback: it must only read cached state,
        never call Zenoh APIs (that can deadlock the session) or block."""
        self._status_fn = fn

    def beat(self) -> None:
        """The main loop went round: called once per iteration (a store; no lock needed)."""
        self._beat_s = time.monotonic()

    def loop_age_s(self) -> float:
        """Seconds since the last `beat`; -1 before the first."""
        beat_s = self._beat_s
        return -1.0 if beat_s is None else time.monotonic() - beat_s

    def report(self) -> ServiceHealth:
        with self._lock:
            inputs = [m.to_proto() for m in self._inputs]
        level = worst(*(i.level for i in inputs))
        messages = [f"{i.key_expr}: {HealthLevel.Name(i.level)}" for i in inputs if i.level != NOMINAL]
        loop_age_s = self.loop_age_s()
        if loop_age_s > LOOP_STALLED_AFTER_S:  # the loop is stuck; Zenoh's threads still answer this
            level = worst(level, CRITICAL)
            messages.insert(0, f"main loop stalled for {loop_age_s:.1f} s")
        if self._status_fn is not None:
            own_level, own_message = self._status_fn()
            level = worst(level, own_level)
            if own_message:
                messages.insert(0, own_message)
        health = ServiceHealth(
            service=self.service,
            instance=self.instance,
            level=level,
            message="; ".join(messages),
            uptime_s=time.monotonic() - self.started_s,
            pid=os.getpid(),
            version=self.version,
            inputs=inputs,
            counters=[Counter(name=k, value=v) for k, v in sorted(self.counters.snapshot().items())],
            loop_age_s=loop_age_s,
        )
        health.header.stamp.GetCurrentTime()
        return health

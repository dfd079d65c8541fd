"""Which simulation ticks a sensor captures on: its rate, and the capture demand of its consumers.

A sensor at `rate_hz` fires on the first tick of each 1/rate period (`fires`), so every sensor of one
rate fires on the same ticks and an agent's frames join tick-exactly. A consumer may ask for only every
n-th of those frames (`rmmdet.v1.CaptureDemand`, the software counterpart of a camera trigger line):
the sensor then captures where `frame_due` holds, which the consumer computes the same way to know
which frames to wait for. Sensors thinned so are staggered by their `phase` (the scene gives each
sensor its index among its agent's sensors of its kind): with 4 cameras asked for every 10th frame,
one camera captures on each of 4 frames in 10 instead of all four on one frame, so neither the
rendering nor the MEC's detector work comes in bursts that miss the join and the latency budget.

`CaptureDemands` is the sensor's side: the demands it has heard, each valid until its `valid_for_s`
runs out; the smallest `every_n` of the valid ones wins (a consumer that needs every frame is never
starved by one that needs fewer), and with none the sensor captures every frame. `DemandRenewal` is
the consumer's side: when to (re)send its demand so that it never lapses while the consumer lives.

    >>> [t for t in range(0, 61) if frame_due(10.0, 5, t, 60.0)]
    [0, 30, 60]
    >>> [t for t in range(0, 61) if frame_due(10.0, 5, t, 60.0, phase=1)]
    [6, 36]
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any


def fires(rate_hz: float, tick: int, tick_hz: float) -> bool:
    """True on the first tick of each 1/rate period (tick 0 included)."""
    return tick == 0 or int(tick * rate_hz / tick_hz) != int((tick - 1) * rate_hz / tick_hz)


def frame_due(
    rate_hz: float, every_n: int, tick: int, tick_hz: float, phase: int = 0, tick_offset: int = 0
) -> bool:
    """True if a sensor at `rate_hz` captures on `tick` when only every `every_n`-th frame is wanted:
    the ticks on which it fires and its frame index floor(tick * rate_hz / tick_hz) is `phase` modulo n.
    A sensor `tick_offset` ticks late does all that on `tick - tick_offset` (nothing before it)."""
    if every_n < 1:
        raise ValueError(f"every_n must be >= 1, got {every_n}")
    t = tick - tick_offset
    return t >= 0 and fires(rate_hz, t, tick_hz) and (int(t * rate_hz / tick_hz) - phase) % every_n == 0


@dataclass
class _Demand:
    every_n: int
    until_s: float


MAX_EVERY_N = 100  # a demand thins a sensor to every 100th frame at most (the MECs ask for 1 or 10)
MAX_VALID_FOR_S = 10.0  # ... for 10 s at most (DemandRenewal's 3 s): a forged demand lapses soon
MAX_CONSUMERS = 32  # demands held at once (a consumer per MEC and viewer): the table does not grow


class CaptureDemands:
    """The capture demands a sensor group has heard, by consumer. Times: monotonic wall seconds.

    Bounded: `every_n` up to MAX_EVERY_N, validity up to MAX_VALID_FOR_S, at most MAX_CONSUMERS
    consumers' demands held (a new consumer's is refused while that many are valid); anything else is
    refused (the caller counts it)."""

    def __init__(self) -> None:
        self._demands: dict[str, _Demand] = {}

    def on_demand(self, consumer: str, every_n: int, valid_for_s: float, now_s: float) -> bool:
        """Record `consumer`'s demand; False (ignored) if it is malformed, out of bounds, or the table
        is full."""
        if not 1 <= every_n <= MAX_EVERY_N or not 0 < valid_for_s <= MAX_VALID_FOR_S:
            return False
        if consumer not in self._demands and len(self._demands) >= MAX_CONSUMERS:
            self.every_n(now_s)  # drops the lapsed ones
            if len(self._demands) >= MAX_CONSUMERS:
                return False
        self._demands[consumer] = _Demand(every_n, now_s + valid_for_s)
        return True

    def take(self, received: Iterable[Any], now_s: float) -> int:
        """`on_demand` for each received CaptureDemand (a bus item: `.header.source_id` names the
        consumer, `.message` is the demand); the number refused."""
        return sum(
            not self.on_demand(r.header.source_id, r.message.every_n, r.message.valid_for_s, now_s)
            for r in received
        )

    def every_n(self, now_s: float) -> int:
        """Smallest `every_n` of the demands still valid at `now_s`; 1 (every frame) with none."""
        for name in [n for n, d in self._demands.items() if d.until_s < now_s]:
            del self._demands[name]
        return min((d.every_n for d in self._demands.values()), default=1)


class DemandRenewal:
    """When a consumer sends its capture demand: at once when its `every_n` changes, else every
    `renew_s`; each demand is valid for `valid_for_s` (> `renew_s`, so one lost message does not let
    it lapse, while a consumer gone for `valid_for_s` stops thinning its sensors). Monotonic seconds."""

    def __init__(self, renew_s: float = 1.0, valid_for_s: float = 3.0) -> None:
        if not 0 < renew_s < valid_for_s:
            raise ValueError(f"need 0 < renew_s < valid_for_s, got {renew_s}, {valid_for_s}")
        self.renew_s = renew_s
        self.valid_for_s = valid_for_s
        self._sent_s = -float("inf")

    def due(self, now_s: float, changed: bool) -> bool:
        """True if the demand should be sent now (then it counts as sent)."""
        if not changed and now_s - self._sent_s < self.renew_s:
            return False
        self._sent_s = now_s
        return True

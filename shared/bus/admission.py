"""`NewcomerAdmission`: how fast a service takes on clients it keeps no state for yet (a token bucket).

A request from a vehicle the coordinator does not hold costs a route search and, for a shard, a release
round across the other shards; one from a vehicle it holds is what the service is for. Without a bound,
a flood of made-up vehicle ids (any client may send one on a profile without access control) costs
CPU in proportion to the flood and delays every real vehicle's answer (issue 52 item 10). So newcomers
are taken at most `rate_per_s` a second on average, `burst` at once; a refused one is told at once
(cheaply: no search) and asks again at its next lane. Known clients are never charged. Seconds are any
monotonic clock's.
"""

from __future__ import annotations

import threading


class NewcomerAdmission:
    """A token bucket of `burst` tokens refilled at `rate_per_s`; thread-safe (Zenoh threads call it)."""

    def __init__(self, rate_per_s: float, burst: int) -> None:
        if rate_per_s <= 0 or burst < 1:
            raise ValueError(f"rate {rate_per_s}/s and burst {burst}: both must be positive")
        self.rate_per_s, self.burst = rate_per_s, burst
        self._tokens = float(burst)
        self._last_s: float | None = None
        self._lock = threading.Lock()
        self.admitted = 0
        self.refused = 0

    def admit(self, now_s: float) -> bool:
        """Take one newcomer at `now_s` if a token is left (True), else refuse it (False)."""
        with self._lock:
            if self._last_s is not None:
                elapsed_s = max(0.0, now_s - self._last_s)
                self._tokens = min(float(self.burst), self._tokens + elapsed_s * self.rate_per_s)
            self._last_s = now_s if self._last_s is None else max(self._last_s, now_s)
            if self._tokens >= 1.0:
                self._tokens -= 1.0
                self.admitted += 1
                return True
            self.refused += 1
            return False

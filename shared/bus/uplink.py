"""Is this process connected to the bus? The session's transports, as Zenoh reports them opening and
closing (`SessionInfo.declare_transport_events_listener`).

A router restart cuts every client off at once: each sees all remote liveliness tokens vanish and
every put go nowhere, although no other process failed. A service that knows it is itself cut off does
not blame the others: presence losses are held until the link has been back long enough for the others'
tokens to return (`shared/bus/liveliness.py`), the coordinator does not demote agents it cannot hear
(`shared/traffic/coverage.py`), and pushed plans are not resent into the void. Times: monotonic s.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

log = logging.getLogger(__name__)

#: After the link returns, how long others get to come back (their clients retry on the same schedule,
#: 0.25 s doubling to 1 s: deploy/zenoh/client.json5) before what vanished with the link is believed, s.
REJOIN_GRACE_S = 2.0


class Uplink:
    """The open transports of one session; thread-safe (Zenoh's callback thread writes, loops read).

    Parameters
    ----------
    clock : callable
        Monotonic seconds.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._open: set[str] = set()
        self._changed_s = clock()  # when `connected` last changed (start: not connected)
        self.outages = 0  # times the last transport closed

    def on_transport(self, peer_id: str, opened: bool) -> None:
        """A transport to `peer_id` opened or closed."""
        with self._lock:
            was = bool(self._open)
            if opened:
                self._open.add(peer_id)
            else:
                self._open.discard(peer_id)
            now_connected = bool(self._open)
            if now_connected != was:
                self._changed_s = self._clock()
                self.outages += not now_connected
        if now_connected != was:
            log.warning("bus link %s", "up" if now_connected else "DOWN: every peer unreachable")

    @property
    def connected(self) -> bool:
        with self._lock:
            return bool(self._open)

    def settled(self, grace_s: float, now_s: float | None = None) -> bool:
        """Connected for at least `grace_s`: what was lost while cut off has had time to come back."""
        now = self._clock() if now_s is None else now_s
        with self._lock:
            return bool(self._open) and now - self._changed_s >= grace_s

    def recovering(self, grace_s: float, now_s: float | None = None) -> bool:
        """Cut off now, or connected again after an outage for less than `grace_s` (never before the
        first outage: a session that just started has lost nothing)."""
        now = self._clock() if now_s is None else now_s
        with self._lock:
            return not self._open or (self.outages > 0 and now - self._changed_s < grace_s)

    def down_for_s(self, now_s: float | None = None) -> float:
        """How long the session has been cut off (0 while connected)."""
        now = self._clock() if now_s is None else now_s
        with self._lock:
            return 0.0 if self._open else now - self._changed_s

"""Is this process connected to the bus? The session's transports, as Zenoh reports them opening and
closing (`SessionInfo.declare_transport_events_listener`).

A router restart cuts every client off at once: each sees all remote liveliness tokens vanish and
every put go nowhere, although no other process failed. A service that knows it is itself cut off does
not blame the others: presence losses are held until the link has been back long enough for the others'
tokens to return (`shared/bus/liveliness.py`), the coordinator does not demote agents it cannot hear
(`shared/traffic/coverage.py`), and pushed plans are not resent into the void. Times: monotonic s.

A frozen router (stopped, or its host stalled) closes nothing: the transports stay open until their
lease runs out (Zenoh's default 10 s) while nothing arrives. A service that normally hears the bus many
times a second (the coordinator: object lists, the sim clock) says so (`expect_traffic`); then a
silence of every input at once is taken as the link's fault, not every sender's, for as long as the
lease could hide it (`silent`), and counts as being cut off.
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
        self._silent_after_s: float | None = None  # expect_traffic
        self._silence_max_s = 0.0
        self._heard_s: float | None = None  # the last sample from the bus
        self._silence_ended_s = 0.0
        self.silences = 0  # silences of every input longer than `silent_after_s`

    def expect_traffic(self, silent_after_s: float, max_s: float) -> None:
        """This service hears the bus at least every `silent_after_s` while the link works: a longer
        silence of everything is the link's (`silent`) for up to `max_s` (longer than the transport's
        lease, after which a frozen peer's transport closes and `connected` tells)."""
        if silent_after_s <= 0 or max_s <= 0:
            raise ValueError("silent_after_s and max_s must be > 0")
        with self._lock:
            self._silent_after_s, self._silence_max_s = silent_after_s, max_s
            self._heard_s = None  # silences count from the next sample on

    def heard(self, now_s: float | None = None) -> None:
        """A sample arrived from the bus (any input, valid or not: the link carried it). Called for every
        sample of every subscription: a service that expects no traffic returns at once (the attribute
        is read without the lock: it is set once, and `expect_traffic` forgets what came before)."""
        if self._silent_after_s is None:
            return
        now = self._clock() if now_s is None else now_s
        with self._lock:
            after = self._silent_after_s
            if after is not None and self._heard_s is not None and now - self._heard_s > after:
                self._silence_ended_s = now
                self.silences += 1
                log.warning("bus heard again after %.2f s of silence", now - self._heard_s)
            self._heard_s = now

    def _silent(self, now: float) -> bool:
        if self._silent_after_s is None or self._heard_s is None or not self._open:
            return False
        quiet_s = now - self._heard_s
        return self._silent_after_s < quiet_s <= self._silent_after_s + self._silence_max_s

    def silent(self, now_s: float | None = None) -> bool:
        """Connected, but nothing heard for longer than `expect_traffic`'s `silent_after_s` (and not
        yet for its `max_s` more): the link, not every sender, is suspected."""
        now = self._clock() if now_s is None else now_s
        with self._lock:
            return self._silent(now)

    def cut_off(self, now_s: float | None = None) -> bool:
        """No open transport, or a silent one (`silent`): a send now likely goes nowhere."""
        now = self._clock() if now_s is None else now_s
        with self._lock:
            return not self._open or self._silent(now)

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
        """Cut off now (`cut_off`), or connected again after an outage or heard again after a silence
        for less than `grace_s` (never before the first: a session that just started has lost nothing)."""
        now = self._clock() if now_s is None else now_s
        with self._lock:
            return (
                not self._open
                or self._silent(now)
                or (self.outages > 0 and now - self._changed_s < grace_s)
                or (self.silences > 0 and now - self._silence_ended_s < grace_s)
            )

    def down_for_s(self, now_s: float | None = None) -> float:
        """How long the session has been cut off (0 while connected)."""
        now = self._clock() if now_s is None else now_s
        with self._lock:
            return 0.0 if self._open else now - self._changed_s

"""Presence: who is alive on the bus, from Zenoh liveliness tokens.

A SIGKILLed process's token disappears within milliseconds (the OS closes its socket); a frozen one
only after the 10 s link lease, and a hung Python loop never — so presence complements, never
replaces, the data-rate watchdogs in shared.bus.health.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import zenoh

from shared.bus import names
from shared.bus.codec import Counters
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.bus.streams import get_stream
from shared.bus.uplink import REJOIN_GRACE_S, Uplink

log = logging.getLogger(__name__)

ChangeFn = Callable[[str, bool], None]


#: Presence changes kept between two `changes()` calls of a service loop (oldest dropped beyond).
CHANGE_QUEUE = 256
#: A vanished token is reported this much later at the soonest (with an uplink): long enough for the
#: transport-closed event that may come just after the tokens' deletions when the link itself failed.
LEAVE_HOLD_S = 0.1


class LivelinessMonitor:
    """Tracks the live tokens under a key expression; optional callback on join/leave.

    The callback runs on a Zenoh thread: it must only record or enqueue. With `queue_changes` the
    monitor enqueues every join/leave itself and a service loop takes them with `changes()`.

    With an `uplink` (`shared/bus/uplink.py`) leaves are debounced: a vanished token still counts as
    alive until a `changes()` call at least `leave_hold_s` after it left at which this session's link
    has been up for `rejoin_grace_s`; a token back before then never left (`blips_absorbed` counts
    them). A killed process is reported `leave_hold_s` late; a router restart, which takes every token
    from every client at once, is not reported at all if the tokens return within the grace.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        on_change: ChangeFn | None = None,
        *,
        queue_changes: bool = False,
        counters: Counters | None = None,
        uplink: Uplink | None = None,
        leave_hold_s: float = LEAVE_HOLD_S,
        rejoin_grace_s: float = REJOIN_GRACE_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if leave_hold_s < 0 or rejoin_grace_s < 0:
            raise ValueError("leave_hold_s and rejoin_grace_s must be >= 0")
        self._lock = threading.Lock()
        self._alive: dict[str, float] = {}
        self._uplink = uplink
        self.leave_hold_s = leave_hold_s
        self.rejoin_grace_s = rejoin_grace_s
        self._leaving: dict[str, float] = {}  # held leaves: token key -> when it vanished
        self._clock = clock
        self.blips_absorbed = 0
        self._on_change = on_change
        self._changes: BoundedQueue[tuple[str, bool]] | None = (
            BoundedQueue(CHANGE_QUEUE, OverflowPolicy.DROP_OLDEST, counters, "dropped/presence_changes")
            if queue_changes
            else None
        )
        self.joins = 0
        self.leaves = 0
        self._subscriber = session.liveliness().declare_subscriber(key_expr, self._on_sample, history=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self.on_token(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

    def on_token(self, key: str, alive: bool) -> None:
        """A token under the key expression appeared (`alive`) or vanished (Zenoh's thread)."""
        with self._lock:
            if alive:
                blip = self._leaving.pop(key, None) is not None
                self.blips_absorbed += blip
                self._alive[key] = self._clock()
                self.joins += 1
            else:
                self.leaves += 1
                blip = False
                if self._uplink is not None and key in self._alive:
                    self._leaving[key] = self._clock()  # reported by `changes` if it stays away
                    log.info("left (held) %s", key)
                    return
                self._alive.pop(key, None)
        if blip:
            log.info("back within the hold, never reported gone: %s", key)
            return
        self._report(key, alive)

    def _report(self, key: str, alive: bool) -> None:
        log.info("%s %s", "joined" if alive else "left", key)
        if self._changes is not None:
            self._changes.put((key, alive))
        if self._on_change is not None:
            self._on_change(key, alive)

    def _release(self) -> None:
        """Report the held leaves that are due (see the class doc)."""
        if self._uplink is None or not self._leaving or not self._uplink.settled(self.rejoin_grace_s):
            return
        now = self._clock()
        with self._lock:
            due = [k for k, left_s in self._leaving.items() if now - left_s >= self.leave_hold_s]
            for key in due:
                del self._leaving[key]
                self._alive.pop(key, None)
        for key in due:
            self._report(key, False)

    def changes(self) -> list[tuple[str, bool]]:
        """The (token key, alive) changes since the last call, oldest first (needs `queue_changes`)."""
        if self._changes is None:
            raise RuntimeError("this monitor was made without queue_changes")
        self._release()
        return self._changes.drain()

    def alive(self) -> list[str]:
        self._release()
        with self._lock:
            return sorted(self._alive)

    def is_alive(self, key: str) -> bool:
        self._release()
        with self._lock:
            return key in self._alive

    def undeclare(self) -> None:
        self._subscriber.undeclare()


def alive_tokens(session: zenoh.Session, key_expr: str, timeout_s: float = 2.0) -> list[str]:
    """Snapshot of the live tokens under `key_expr`."""
    replies = session.liveliness().get(key_expr, timeout=timeout_s)
    return sorted(str(r.ok.key_expr) for r in replies if r.ok is not None)


def agent_of_mec_token(key: str) -> str | None:
    """The agent of a MEC's presence token (`rmmdet/v1/<agent>/@alive/mec/<agent>`), None for any
    other key."""
    ids = get_stream("alive").ids(key)
    if ids is None or ids["service"] != names.MEC or ids["scope"] != ids["instance"]:
        return None
    return ids["instance"]


def source_of_token(key: str) -> str | None:
    """The source id (`scope/service/instance`, as `Node.source_id`) whose presence token is `key`;
    None if `key` is not a presence token."""
    ids = get_stream("alive").ids(key)
    return None if ids is None else f"{ids['scope']}/{ids['service']}/{ids['instance']}"

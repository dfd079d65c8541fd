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

from shared.bus.codec import Counters
from shared.bus.queues import BoundedQueue, OverflowPolicy
from shared.bus.streams import get_stream

log = logging.getLogger(__name__)

ChangeFn = Callable[[str, bool], None]


#: Presence changes kept between two `changes()` calls of a service loop (oldest dropped beyond).
CHANGE_QUEUE = 256


class LivelinessMonitor:
    """Tracks the live tokens under a key expression; optional callback on join/leave.

    The callback runs on a Zenoh thread: it must only record or enqueue. With `queue_changes` the
    monitor enqueues every join/leave itself and a service loop takes them with `changes()`.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        on_change: ChangeFn | None = None,
        *,
        queue_changes: bool = False,
        counters: Counters | None = None,
    ) -> None:
        self._lock = threading.Lock()
        self._alive: dict[str, float] = {}
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
        key = str(sample.key_expr)
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            if alive:
                self._alive[key] = time.monotonic()
                self.joins += 1
            else:
                self._alive.pop(key, None)
                self.leaves += 1
        log.info("%s %s", "joined" if alive else "left", key)
        if self._changes is not None:
            self._changes.put((key, alive))
        if self._on_change is not None:
            self._on_change(key, alive)

    def changes(self) -> list[tuple[str, bool]]:
        """The (token key, alive) changes since the last call, oldest first (needs `queue_changes`)."""
        if self._changes is None:
            raise RuntimeError("this monitor was made without queue_changes")
        return self._changes.drain()

    def alive(self) -> list[str]:
        with self._lock:
            return sorted(self._alive)

    def is_alive(self, key: str) -> bool:
        with self._lock:
            return key in self._alive

    def undeclare(self) -> None:
        self._subscriber.undeclare()


def alive_tokens(session: zenoh.Session, key_expr: str, timeout_s: float = 2.0) -> list[str]:
    """Snapshot of the live tokens under `key_expr`."""
    replies = session.liveliness().get(key_expr, timeout=timeout_s)
    return sorted(str(r.ok.key_expr) for r in replies if r.ok is not None)


def agent_of_mec_token(key: str) -> str | None:
    """The agent of a MEC's presence token (`rmmdet/@v1/<agent>/@alive/mec/<agent>`), None for any
    other key."""
    ids = get_stream("alive").ids(key)
    if ids is None or ids["service"] != "mec" or ids["scope"] != ids["instance"]:
        return None
    return ids["instance"]


def source_of_token(key: str) -> str | None:
    """The source id (`scope/service/instance`, as `Node.source_id`) whose presence token is `key`;
    None if `key` is not a presence token."""
    ids = get_stream("alive").ids(key)
    return None if ids is None else f"{ids['scope']}/{ids['service']}/{ids['instance']}"

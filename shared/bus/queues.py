"""Bounded, counted hand-off queues between Zenoh callbacks and worker threads.

Zenoh callbacks must only enqueue (blocking there stalls the whole session, docs/reliability.md (c).5-6),
so every subscription feeds one of these. Nothing is lost silently: every drop is counted.

- `DROP_OLDEST`: latest-wins streams (frames, object lists): a full queue discards its oldest item.
- `REJECT_NEWEST`: must-deliver streams where order matters and the producer can retry: a full
  queue refuses the new item (`put` returns False).

Given `counters`, a queue exports its drops itself (`counters.inc(drop_counter)`, both policies), so a
service's health accounts for every item: what was put = what was taken + what was counted dropped.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from enum import StrEnum
from typing import TYPE_CHECKING, Generic, TypeVar

if TYPE_CHECKING:
    from shared.bus.codec import Counters

T = TypeVar("T")
#: The counter a queue's drops go to unless it is given another name.
DROPPED = "dropped/queue_full"


class OverflowPolicy(StrEnum):
    DROP_OLDEST = "drop_oldest"
    REJECT_NEWEST = "reject_newest"


class BoundedQueue(Generic[T]):
    """Thread-safe FIFO with a hard capacity and drop accounting."""

    def __init__(
        self,
        maxsize: int,
        policy: OverflowPolicy = OverflowPolicy.DROP_OLDEST,
        counters: Counters | None = None,
        drop_counter: str = DROPPED,
    ) -> None:
        if maxsize < 1:
            raise ValueError("maxsize must be >= 1")
        self.maxsize = maxsize
        self.policy = policy
        self._counters = counters
        self._drop_counter = drop_counter
        self._items: deque[T] = deque()
        self._cond = threading.Condition()
        self._closed = False
        self.put_count = 0
        self.dropped = 0  # items discarded (oldest) or refused (newest) because the queue was full

    def put(self, item: T) -> bool:
        """Enqueue without blocking. False if the item was refused (REJECT_NEWEST, full or closed)."""
        with self._cond:
            if self._closed:
                return False
            if len(self._items) >= self.maxsize:
                self.dropped += 1
                if self._counters is not None:
                    self._counters.inc(self._drop_counter)
                if self.policy is OverflowPolicy.REJECT_NEWEST:
                    return False
                self._items.popleft()
            self._items.append(item)
            self.put_count += 1
            self._cond.notify()
            return True

    def get(self, timeout: float | None = None) -> T | None:
        """Oldest item, waiting up to `timeout` seconds (None = forever); None on timeout or close."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while not self._items:
                if self._closed:
                    return None
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._cond.wait(remaining)
            return self._items.popleft()

    def drain(self) -> list[T]:
        with self._cond:
            items = list(self._items)
            self._items.clear()
            return items

    def close(self) -> None:
        """Wake every waiter; later puts are refused, gets return what is left then None."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)

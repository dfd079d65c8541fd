"""Bounded queues: drop-oldest and reject-newest policies, counting, blocking get, close."""

from __future__ import annotations

import threading
import time

import pytest

from shared.bus.codec import Counters
from shared.bus.queues import BoundedQueue, OverflowPolicy


def test_drop_oldest_keeps_the_newest_and_counts() -> None:
    q: BoundedQueue[int] = BoundedQueue(3)
    for i in range(5):
        assert q.put(i)
    assert q.dropped == 2
    assert q.put_count == 5
    assert [q.get(0), q.get(0), q.get(0)] == [2, 3, 4]
    assert q.get(0) is None


def test_reject_newest_refuses_and_counts() -> None:
    q: BoundedQueue[int] = BoundedQueue(2, OverflowPolicy.REJECT_NEWEST)
    assert q.put(1) and q.put(2)
    assert not q.put(3)
    assert q.dropped == 1
    assert q.drain() == [1, 2]


def test_get_waits_for_a_producer_and_times_out() -> None:
    q: BoundedQueue[str] = BoundedQueue(1)
    threading.Timer(0.05, q.put, args=("x",)).start()
    assert q.get(timeout=2.0) == "x"
    t0 = time.monotonic()
    assert q.get(timeout=0.05) is None
    assert time.monotonic() - t0 >= 0.04


def test_close_wakes_waiters_and_refuses_puts() -> None:
    q: BoundedQueue[int] = BoundedQueue(4)
    result: list[int | None] = []
    waiter = threading.Thread(target=lambda: result.append(q.get()))
    waiter.start()
    # Close only once the waiter is blocked inside get(): a close before it would pass vacuously.
    deadline = time.monotonic() + 10.0
    while not q._cond._waiters and time.monotonic() < deadline:  # type: ignore[attr-defined]
        time.sleep(0.001)
    assert q._cond._waiters, "the waiter never blocked in get()"  # type: ignore[attr-defined]
    q.close()
    waiter.join(10.0)
    assert not waiter.is_alive() and result == [None]
    assert not q.put(1)


def test_invalid_size() -> None:
    with pytest.raises(ValueError):
        BoundedQueue(0)


def test_a_queue_with_counters_exports_every_drop() -> None:
    counters = Counters()
    oldest: BoundedQueue[int] = BoundedQueue(2, OverflowPolicy.DROP_OLDEST, counters)
    newest: BoundedQueue[int] = BoundedQueue(2, OverflowPolicy.REJECT_NEWEST, counters, "dropped/acks")
    for i in range(5):
        oldest.put(i)
        newest.put(i)
    assert counters.snapshot() == {"dropped/queue_full": 3, "dropped/acks": 3}
    assert oldest.drain() == [3, 4] and newest.drain() == [0, 1]

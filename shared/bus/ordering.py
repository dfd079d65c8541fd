"""Latest-wins ordering of one source's messages that cannot be latched by one bad message.

A receiver that keeps only what is newer than the newest it has seen (a sensor rendering ticks, the
MEC's tick join, the coordinator's object lists) would otherwise stop for good after a single message
from the far future (a forged tick 2^63, a future stamp) or after a restarted sim whose ticks start
again at 0. Two rules prevent that:

- an `epoch` (the sim run, `Header.epoch`) other than the current one starts the order afresh;
- a position more than `reset_after` behind the newest also starts it afresh: no genuine message
  arrives that late (receivers drop inputs older than their freshness limit long before), so it means
  the newest was bogus or the source restarted. A bogus newest costs at most one message.

Positions are ticks or stamps (ns), whatever the receiver orders by; `reset_after` is in the same unit.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum


class Order(Enum):
    NEWER = "newer"  # take it: newer than the newest of this epoch
    OLDER = "older"  # not newer (a repeat or a late one): latest-wins receivers drop it
    RESTART = "restart"  # a new epoch or far behind: take it and restart the order from it


@dataclass(frozen=True)
class Position:
    epoch: int
    value: int


def order(newest: Position | None, incoming: Position, reset_after: int) -> Order:
    """Where `incoming` stands against the `newest` taken so far (None: nothing taken yet)."""
    if newest is None or incoming.epoch != newest.epoch:
        return Order.RESTART if newest is not None else Order.NEWER
    if incoming.value > newest.value:
        return Order.NEWER
    if newest.value - incoming.value > reset_after:
        return Order.RESTART
    return Order.OLDER


class OrderGate:
    """`order` with its state: `admit` says whether to take a message and keeps the newest taken."""

    def __init__(self, reset_after: int) -> None:
        if reset_after <= 0:
            raise ValueError("reset_after must be > 0")
        self.reset_after = reset_after
        self.newest: Position | None = None
        self.restarts = 0  # orders started afresh (a new epoch, or a bogus newest dropped)

    def admit(self, epoch: int, value: int) -> bool:
        incoming = Position(epoch, value)
        verdict = order(self.newest, incoming, self.reset_after)
        if verdict is Order.OLDER:
            return False
        if verdict is Order.RESTART:
            self.restarts += 1
        self.newest = incoming
        return True


def reset_after_ticks(tick_hz: float | None) -> int:
    """`limits.order_reset_s` in ticks of a sim at `tick_hz` (None, not known yet: the fastest allowed
    rate, the widest window)."""
    from shared.bus.streams import limits  # local: streams loads zenoh

    bus = limits()
    return max(1, round(bus.order_reset_s * (tick_hz or bus.max_tick_hz)))

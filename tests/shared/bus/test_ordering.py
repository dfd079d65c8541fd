"""Latest-wins order that one bogus message or a restarted source cannot latch."""

from __future__ import annotations

import pytest

from shared.bus.ordering import Order, OrderGate, Position, order, reset_after_ticks
from shared.bus.streams import limits


@pytest.mark.parametrize(
    ("newest", "incoming", "expected"),
    [
        (None, Position(1, 5), Order.NEWER),
        (Position(1, 5), Position(1, 6), Order.NEWER),
        (Position(1, 5), Position(1, 5), Order.OLDER),  # a repeat
        (Position(1, 5), Position(1, 0), Order.OLDER),  # late, within the window (10)
        (Position(1, 20), Position(1, 9), Order.RESTART),  # further back than the window
        (Position(1, 5), Position(2, 0), Order.RESTART),  # a new epoch
    ],
)
def test_order_known_answers(newest: Position | None, incoming: Position, expected: Order) -> None:
    assert order(newest, incoming, reset_after=10) is expected


def test_a_bogus_far_future_tick_costs_one_message() -> None:
    gate = OrderGate(reset_after=120)
    assert gate.admit(7, 100) and gate.admit(7, 101)
    assert gate.admit(7, 2**63)  # forged: taken, it is the newest
    assert gate.admit(7, 102)  # the next genuine tick is far behind: the order restarts from it
    assert gate.admit(7, 103) and not gate.admit(7, 103)
    assert gate.restarts == 1


def test_a_restarted_sim_is_taken_at_once() -> None:
    gate = OrderGate(reset_after=120)
    assert gate.admit(1, 5000)
    assert gate.admit(2, 0) and gate.admit(2, 1)  # new epoch: ticks from 0 again
    assert gate.restarts == 1
    # Epochs are not ordered (a forged "newest" epoch would otherwise latch): any change restarts,
    # so a message of another run costs exactly one message of this one.
    assert gate.admit(1, 5001) and gate.admit(2, 2)
    assert gate.restarts == 3


def test_gate_rejects_a_non_positive_window() -> None:
    with pytest.raises(ValueError):
        OrderGate(0)


def test_reset_window_in_ticks() -> None:
    bus = limits()
    assert reset_after_ticks(60.0) == round(bus.order_reset_s * 60)
    assert reset_after_ticks(None) == round(bus.order_reset_s * bus.max_tick_hz)

"""The newcomer admission's token bucket: known answers."""

from __future__ import annotations

import pytest

from shared.bus.admission import NewcomerAdmission


def test_a_burst_then_the_rate() -> None:
    gate = NewcomerAdmission(rate_per_s=10.0, burst=5)
    assert [gate.admit(0.0) for _ in range(7)] == [True] * 5 + [False] * 2
    assert gate.admit(0.05) is False  # half a token
    assert gate.admit(0.1) is True  # one token after 0.1 s at 10/s
    assert [gate.admit(100.0) for _ in range(6)] == [True] * 5 + [False]  # never more than the burst
    assert (gate.admitted, gate.refused) == (11, 4)


def test_a_clock_going_back_gives_no_tokens() -> None:
    gate = NewcomerAdmission(rate_per_s=1.0, burst=1)
    assert gate.admit(10.0) and not gate.admit(5.0) and not gate.admit(10.5)
    assert gate.admit(11.0)


def test_ten_thousand_newcomers_in_a_second_cost_at_most_the_burst_and_the_rate() -> None:
    gate = NewcomerAdmission(rate_per_s=50.0, burst=100)
    admitted = sum(gate.admit(k / 10_000) for k in range(10_000))
    assert 100 <= admitted <= 150


@pytest.mark.parametrize(("rate", "burst"), [(0.0, 1), (1.0, 0), (-1.0, 5)])
def test_nonsense_settings_are_refused(rate: float, burst: int) -> None:
    with pytest.raises(ValueError):
        NewcomerAdmission(rate, burst)

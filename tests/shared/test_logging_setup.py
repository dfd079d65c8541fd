"""ReportTimer, the services' log-every-N-seconds timer: known answers on a hand-driven clock."""

from __future__ import annotations

import pytest

from shared.logging_setup import ReportTimer


def test_due_once_per_interval_from_construction_without_catching_up() -> None:
    now = [100.0]
    timer = ReportTimer(10.0, lambda: now[0])
    due = []
    for t in (100.0, 105.0, 109.9, 110.0, 110.5, 135.0, 136.0, 144.9, 145.0):
        now[0] = t
        due.append(timer.due())
    # due at 110 (one interval after 100); 135 is late by 15 s: one line, not two, and the next
    # interval counts from 135.
    assert due == [False, False, False, True, False, True, False, False, True]


@pytest.mark.parametrize("interval_s", [0.0, -1.0, float("nan")])
def test_an_interval_must_be_positive(interval_s: float) -> None:
    with pytest.raises(ValueError, match="interval_s"):
        ReportTimer(interval_s)

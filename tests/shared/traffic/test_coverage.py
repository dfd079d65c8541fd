"""CoverageTracker: LIVE -> STALE (age or presence gone) -> LOST, and recovery."""

from __future__ import annotations

import math

import pytest

from shared.traffic.config import CoverageConfig
from shared.traffic.coverage import AgentState, CoverageTracker

LIVE, STALE, LOST = AgentState.LIVE, AgentState.STALE, AgentState.LOST


@pytest.fixture
def tracker() -> CoverageTracker:
    return CoverageTracker(["a1", "a2"], CoverageConfig(stale_after_s=0.5, lost_after_s=5.0))


def test_never_seen_is_lost(tracker: CoverageTracker) -> None:
    assert tracker.agents == ["a1", "a2"]
    assert tracker.state("a1", 0.0) is LOST
    assert tracker.age_s("a1", 100.0) == math.inf
    assert tracker.object_count("a1") == 0
    assert tracker.live(0.0) == []
    assert tracker.missing(0.0) == ["a1", "a2"]


@pytest.mark.parametrize(
    ("age_s", "state"),
    [
        (0.0, LIVE),
        (0.4, LIVE),
        (0.5, LIVE),
        (0.6, STALE),
        (4.9, STALE),
        (5.0, STALE),
        (5.1, LOST),
        (60.0, LOST),
    ],
)
def test_state_by_data_age(tracker: CoverageTracker, age_s: float, state: AgentState) -> None:
    tracker.on_data("a1", 10.0, 3)
    assert tracker.state("a1", 10.0 + age_s) is state
    assert tracker.age_s("a1", 10.0 + age_s) == pytest.approx(age_s)
    assert tracker.object_count("a1") == 3


def test_presence_gone_is_stale_at_once_then_lost(tracker: CoverageTracker) -> None:
    tracker.on_presence("a1", True)
    tracker.on_data("a1", 1.0, 2)
    assert tracker.state("a1", 1.0) is LIVE
    tracker.on_presence("a1", False)
    assert tracker.state("a1", 1.0) is STALE  # data still fresh, but the agent is gone
    assert tracker.state("a1", 6.1) is LOST
    # data keeps coming from a process whose token vanished: still not trusted
    tracker.on_data("a1", 7.0, 2)
    assert tracker.state("a1", 7.0) is STALE


def test_recovers_to_live_with_new_data_and_presence(tracker: CoverageTracker) -> None:
    tracker.on_data("a1", 0.0, 4)
    tracker.on_presence("a1", False)
    assert tracker.state("a1", 10.0) is LOST
    tracker.on_presence("a1", True)
    assert tracker.state("a1", 10.0) is LOST  # presence alone is not data
    tracker.on_data("a1", 10.0, 1)
    assert tracker.state("a1", 10.0) is LIVE
    assert tracker.object_count("a1") == 1


def test_live_and_missing_lists(tracker: CoverageTracker) -> None:
    tracker.on_data("a1", 0.0, 1)
    tracker.on_data("a2", 0.3, 1)
    assert tracker.live(0.5) == ["a1", "a2"]
    assert tracker.missing(0.5) == []
    assert tracker.live(0.7) == ["a2"]
    assert tracker.missing(0.7) == ["a1"]
    assert tracker.missing(10.0) == ["a1", "a2"]


def test_unknown_agent_raises(tracker: CoverageTracker) -> None:
    with pytest.raises(KeyError):
        tracker.on_data("ghost", 0.0, 1)

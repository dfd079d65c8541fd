"""Capture cadence: which ticks a sensor captures on, and the demands a sensor group follows."""

from __future__ import annotations

import pytest

from shared.scene.cadence import CaptureDemands, fires, frame_due

TICK_HZ = 60.0


def test_every_nth_frame_falls_on_ticks_where_the_sensor_fires() -> None:
    for every_n in (1, 2, 5):
        due = [t for t in range(600) if frame_due(10.0, every_n, t, TICK_HZ)]
        assert due == [t for t in range(600) if fires(10.0, t, TICK_HZ)][::every_n]


def test_every_fifth_frame_at_10_hz_is_every_half_second() -> None:
    assert [t for t in range(121) if frame_due(10.0, 5, t, TICK_HZ)] == [0, 30, 60, 90, 120]


def test_every_n_below_one_is_rejected() -> None:
    with pytest.raises(ValueError):
        frame_due(10.0, 0, 6, TICK_HZ)


def test_no_demand_means_every_frame() -> None:
    assert CaptureDemands().every_n(now_s=0.0) == 1


def test_the_smallest_valid_demand_wins_and_demands_lapse() -> None:
    demands = CaptureDemands()
    assert demands.on_demand("agent1/mec", 5, valid_for_s=3.0, now_s=10.0)
    assert demands.every_n(now_s=11.0) == 5
    assert demands.on_demand("viewer", 2, valid_for_s=1.0, now_s=11.0)
    assert demands.every_n(now_s=11.5) == 2  # a consumer needing more frames is never starved
    assert demands.every_n(now_s=12.5) == 5  # the viewer's demand lapsed
    assert demands.every_n(now_s=13.5) == 1  # and the MEC's: every frame again


def test_a_renewed_demand_replaces_the_consumers_earlier_one() -> None:
    demands = CaptureDemands()
    demands.on_demand("agent1/mec", 5, valid_for_s=3.0, now_s=10.0)
    demands.on_demand("agent1/mec", 1, valid_for_s=3.0, now_s=11.0)  # its lidar died
    assert demands.every_n(now_s=11.0) == 1


def test_malformed_demands_are_refused() -> None:
    demands = CaptureDemands()
    assert not demands.on_demand("x", 0, valid_for_s=3.0, now_s=0.0)
    assert not demands.on_demand("x", 5, valid_for_s=0.0, now_s=0.0)
    assert not demands.on_demand("x", 5, valid_for_s=float("nan"), now_s=0.0)
    assert demands.every_n(now_s=0.0) == 1

"""Capture cadence: which ticks a sensor captures on, and the demands a sensor group follows."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from shared.paths import DEFAULT_SCENE
from shared.scene.cadence import (
    MAX_CONSUMERS,
    MAX_EVERY_N,
    MAX_VALID_FOR_S,
    CaptureDemands,
    DemandRenewal,
    fires,
    frame_due,
)
from shared.scene.scene import Scene

TICK_HZ = 60.0


def test_every_nth_frame_falls_on_ticks_where_the_sensor_fires() -> None:
    for every_n in (1, 2, 5):
        due = [t for t in range(600) if frame_due(10.0, every_n, t, TICK_HZ)]
        assert due == [t for t in range(600) if fires(10.0, t, TICK_HZ)][::every_n]


def test_every_fifth_frame_at_10_hz_is_every_half_second() -> None:
    assert [t for t in range(121) if frame_due(10.0, 5, t, TICK_HZ)] == [0, 30, 60, 90, 120]


def test_phases_stagger_the_sensors_over_the_n_frames() -> None:
    fired = [t for t in range(600) if fires(10.0, t, TICK_HZ)]
    for every_n in (1, 3, 5):
        by_phase = [
            [t for t in range(600) if frame_due(10.0, every_n, t, TICK_HZ, phase)] for phase in range(every_n)
        ]
        # Each fired frame belongs to exactly one phase; phase p takes frames p, p + n, ...
        assert sorted(t for ticks in by_phase for t in ticks) == fired
        assert all(ticks == fired[p::every_n] for p, ticks in enumerate(by_phase))
    # A phase beyond n wraps around: with n = 1 every phase captures every frame.
    assert [t for t in range(60) if frame_due(10.0, 1, t, TICK_HZ, phase=3)] == fired[:10]
    assert [t for t in range(61) if frame_due(10.0, 5, t, TICK_HZ, phase=6)] == [6, 36]


def test_scene_sensors_of_one_agent_and_kind_take_consecutive_phases() -> None:
    scene = Scene.load(DEFAULT_SCENE)
    cameras = scene.sensors_of("agent1", "camera")
    assert len(cameras) == 4
    # Every 5th frame: camera i on frames i, i + 5, ...; frame 4 of each 5 has no camera.
    due = [{c.id for c in cameras if scene.captures_on(c, k * 6, TICK_HZ, 5)} for k in range(10)]
    assert due == [{c.id} for c in cameras] + [set()] + [{c.id} for c in cameras] + [set()]
    # Every frame: all of them.
    assert all(scene.captures_on(c, 6, TICK_HZ) for c in cameras)
    # Lidars are numbered among lidars, not after the cameras.
    lidars = scene.sensors_of("agent1", "lidar")
    assert [scene.captures_on(lid, 0, TICK_HZ, 2) for lid in lidars] == [True, False]
    # The spec's own rate counts (a dataset run samples cameras at 1 Hz).
    slow = cameras[0].model_copy(update={"rate_hz": 1.0})
    assert [t for t in range(121) if scene.captures_on(slow, t, TICK_HZ)] == [0, 60, 120]


def test_a_late_sensor_fires_on_the_same_cadence_shifted() -> None:
    assert [t for t in range(25) if frame_due(10.0, 1, t, TICK_HZ, tick_offset=2)] == [2, 8, 14, 20]
    assert [t for t in range(70) if frame_due(10.0, 5, t, TICK_HZ, phase=1, tick_offset=4)] == [10, 40]
    assert not frame_due(10.0, 1, 0, TICK_HZ, tick_offset=2)  # nothing before its first tick


def test_agents_fire_on_their_own_phases_and_together_cover_the_sensor_ticks() -> None:
    scene = Scene.load(DEFAULT_SCENE)
    fired = {
        a: sorted({t for t in range(60) for s in scene.sensors_of(a) if scene.captures_on(s, t, TICK_HZ)})
        for a in scene.agents
    }
    offsets = {a: scene.agents[a].sensor_phase_ticks for a in scene.agents}
    assert len(set(offsets.values())) == len(offsets)  # no two agents on one tick
    for agent, ticks in fired.items():
        assert ticks == list(range(offsets[agent], 60, 6))  # all its sensors on one tick, at 10 Hz
    for t in range(60):
        assert scene.agents_capturing_on(t, TICK_HZ) == {a for a, ticks in fired.items() if t in ticks}


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


def test_take_records_received_demands_and_counts_the_refused() -> None:
    def received(consumer: str, every_n: int, valid_for_s: float) -> SimpleNamespace:
        return SimpleNamespace(
            header=SimpleNamespace(source_id=consumer),
            message=SimpleNamespace(every_n=every_n, valid_for_s=valid_for_s),
        )

    demands = CaptureDemands()
    items = [received("mec-a", 5, 3.0), received("mec-b", 0, 3.0), received("mec-c", 2, -1.0)]
    assert demands.take(items, 0.0) == 2  # every_n 0 and a negative validity refused
    assert demands.every_n(1.0) == 5
    assert demands.take([], 1.0) == 0


def test_demands_are_bounded_in_cadence_validity_and_number() -> None:
    """Issue 34, item 9: one forged `every_n = 1` demand valid for ever disabled camera thinning for
    good, and every new source id grew the table."""
    demands = CaptureDemands()
    assert not demands.on_demand("x", 1, valid_for_s=1e9, now_s=0.0)
    assert not demands.on_demand("x", MAX_EVERY_N + 1, valid_for_s=3.0, now_s=0.0)
    assert demands.on_demand("x", MAX_EVERY_N, valid_for_s=MAX_VALID_FOR_S, now_s=0.0)
    assert demands.every_n(now_s=MAX_VALID_FOR_S + 0.1) == 1  # lapsed
    for k in range(MAX_CONSUMERS):
        assert demands.on_demand(f"c{k}", 10, valid_for_s=3.0, now_s=20.0)
    assert not demands.on_demand("one too many", 1, valid_for_s=3.0, now_s=20.0)
    assert demands.on_demand("c0", 5, valid_for_s=3.0, now_s=22.0)  # a known consumer renews
    assert demands.on_demand("newcomer", 10, valid_for_s=3.0, now_s=24.5)  # the rest lapsed meanwhile
    assert demands.every_n(now_s=24.5) == 5


def test_demand_renewal_sends_at_once_on_change_and_every_renew_period() -> None:
    renewal = DemandRenewal(renew_s=1.0, valid_for_s=3.0)
    assert renewal.due(10.0, changed=False)  # first call: never sent yet
    assert not renewal.due(10.5, changed=False)
    assert renewal.due(10.6, changed=True)  # a new every_n goes out at once
    assert not renewal.due(11.5, changed=False)
    assert renewal.due(11.6, changed=False)  # renewed a period after the last send


def test_demand_renewal_rejects_a_validity_shorter_than_the_renewal() -> None:
    with pytest.raises(ValueError):
        DemandRenewal(renew_s=3.0, valid_for_s=1.0)

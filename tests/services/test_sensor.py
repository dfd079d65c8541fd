"""Sensor service shell: group parsing and latest-wins tick selection (no bus)."""

from __future__ import annotations

import pytest
from rmmdet.v1.common_pb2 import Header
from rmmdet.v1.sim_pb2 import GroundTruth

from services.sensor.main import newest_due
from shared.bus.node import Received
from shared.config import ConfigError
from shared.paths import DEFAULT_SCENE
from shared.scene.scene import Scene


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.load(DEFAULT_SCENE)


def received(tick: int) -> Received:
    gt = GroundTruth(tick_hz=60.0)
    gt.header.tick = tick
    return Received("rmmdet/v1/sim/ground_truth", gt, Header(tick=tick), 0, 0)


def parse_group(scene: Scene, group: str, only: str | None = None) -> list:
    return scene.group_sensors(group, only)


def test_groups_name_an_agent_and_a_sensor_kind(scene: Scene) -> None:
    assert [s.id for s in parse_group(scene, "agent1-lidars")] == ["lidar_11", "lidar_12"]
    assert [s.id for s in parse_group(scene, "agent2-radars")] == ["radar_2", "radar_3"]
    assert len(parse_group(scene, "agent3-cameras")) == 4
    for bad in ("agent9-cameras", "agent1-sonars", "agent1", "agent3-radars"):
        with pytest.raises(ConfigError):
            parse_group(scene, bad)
    assert [s.id for s in parse_group(scene, "agent2-radars", only="radar_3")] == ["radar_3"]
    with pytest.raises(ConfigError, match="cam_2"):
        parse_group(scene, "agent2-radars", only="radar_2,cam_2")  # not in the group


def test_newest_due_tick_wins_and_earlier_due_ticks_count_as_skipped(scene: Scene) -> None:
    lidars = parse_group(scene, "agent1-lidars")
    assert {s.rate_hz for s in lidars} == {10.0}  # at 60 Hz ticks: due on ticks 0, 6, 12, 18, ...
    due, skipped = newest_due([received(t) for t in (5, 6, 7, 11, 12, 13)], scene, lidars)
    assert due is not None and due.message.header.tick == 12 and skipped == 1
    due, skipped = newest_due([received(t) for t in (7, 8, 9)], scene, lidars)
    assert due is None and skipped == 0


def test_a_capture_demand_thins_the_due_ticks(scene: Scene) -> None:
    cameras = parse_group(scene, "agent1-cameras")
    # Every 5th frame at 10 Hz on 60 Hz ticks, the 4 cameras staggered: camera i on frame i of each 5
    # (ticks 6 i, 30 + 6 i, ...); frame 4 (tick 24, 54, ...) is no camera's.
    due, skipped = newest_due([received(t) for t in (24, 25, 26)], scene, cameras, every_n=5)
    assert due is None and skipped == 0
    due, skipped = newest_due([received(t) for t in (6, 12, 24, 25)], scene, cameras, every_n=5)
    assert due is not None and due.message.header.tick == 12 and skipped == 1
    first_only = cameras[:1]
    due, skipped = newest_due([received(t) for t in (6, 12, 18, 24)], scene, first_only, every_n=5)
    assert due is None and skipped == 0

"""Radar model on the sand table (radar_3: at (1.96, -1.45, 0.28), boresight +y world, left = -x)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from shared.scene.scene import Scene
from sim.sensors.radar import RadarSimulator, SimRadarTarget, VehicleState, to_radar_scan
from sim.world import StaticWorld, VehiclePose, VehicleWorld

RADAR = "radar_3"
CENTRE_Z_M = 0.105  # box centre of a vehicle on the table
NOISE_FREE: dict[str, Any] = {
    "range_noise_std_m": 0.0,
    "azimuth_noise_std_rad": 0.0,
    "range_rate_noise_std_mps": 0.0,
    "rcs_noise_std_db": 0.0,
    "detection_probability": 1.0,
    "clutter_per_scan": 0.0,
}


@pytest.fixture(scope="module")
def worlds(static: StaticWorld, vehicles: VehicleWorld) -> tuple[StaticWorld, VehicleWorld]:
    return static, vehicles


@pytest.fixture
def sim(scene: Scene, worlds: tuple[StaticWorld, VehicleWorld]) -> RadarSimulator:
    """radar_3 without noise, misses or clutter (tests add what they need)."""
    radar = RadarSimulator(scene, RADAR, *worlds)
    radar.model = radar.model.model_copy(update=NOISE_FREE)
    return radar


def ahead(distance_m: float, azimuth_rad: float = 0.0) -> tuple[float, float]:
    """World xy at a horizontal distance and azimuth from radar_3 (boresight +y, left = -x)."""
    return 1.96 - distance_m * math.sin(azimuth_rad), -1.45 + distance_m * math.cos(azimuth_rad)


def state(
    vid: str, xy: tuple[float, float], yaw: float = math.pi / 2, v: tuple[float, float, float] = (0, 0, 0)
) -> VehicleState:
    return VehicleState(vid, np.array([*xy, CENTRE_Z_M]), yaw, 0.0, np.asarray(v, dtype=float))


def scan(radar: RadarSimulator, states: list[VehicleState], seed: int = 0) -> list[SimRadarTarget]:
    radar.vehicles.update([VehiclePose(s.vehicle_id, tuple(s.center_m), s.yaw_rad) for s in states])
    return radar.scan(states, np.random.default_rng(seed))


def by_vehicle(targets: list[SimRadarTarget]) -> dict[str, SimRadarTarget]:
    return {t.vehicle_id: t for t in targets if not t.is_clutter}


def test_range_rate_sign_and_magnitude(sim: RadarSimulator) -> None:
    xy = (1.96, 0.3)  # on the boresight, 1.75 m ahead
    approaching = by_vehicle(scan(sim, [state("a", xy, v=(0, -0.5, 0))]))["a"]
    receding = by_vehicle(scan(sim, [state("a", xy, v=(0, 0.5, 0))]))["a"]
    crossing = by_vehicle(scan(sim, [state("a", xy, v=(0.5, 0, 0))]))["a"]
    assert abs(approaching.azimuth_rad) < 1e-3
    assert approaching.range_rate_mps < 0 < receding.range_rate_mps
    # The line of sight dips ~0.04 rad to the vehicle: |range rate| = |v| cos(dip).
    assert abs(approaching.range_rate_mps) == pytest.approx(0.5, rel=0.01)
    assert abs(receding.range_rate_mps) == pytest.approx(0.5, rel=0.01)
    assert abs(crossing.range_rate_mps) < 1e-3
    assert approaching.range_m == pytest.approx(1.75 - 0.165, abs=0.01)  # to the front face


def test_range_rate_sign_with_noise(scene: Scene, worlds: tuple[StaticWorld, VehicleWorld]) -> None:
    radar = RadarSimulator(scene, RADAR, *worlds)
    radar.model = radar.model.model_copy(update={"detection_probability": 1.0, "clutter_per_scan": 0.0})
    for seed in range(10):
        t = by_vehicle(scan(radar, [state("a", (1.96, 0.3), v=(0, -0.4, 0))], seed))["a"]
        assert t.range_rate_mps == pytest.approx(-0.4, abs=0.05)


def test_azimuth_sign(sim: RadarSimulator) -> None:
    left = by_vehicle(scan(sim, [state("l", ahead(2.0, 0.45))]))["l"]
    assert left.azimuth_rad == pytest.approx(0.45, abs=0.08)
    # To the right the building_e occludes; switch occlusion off to see the sign.
    sim.model = sim.model.model_copy(update={"occlusion_max_fraction": 1.0})
    right = by_vehicle(scan(sim, [state("r", ahead(2.0, -0.3))]))["r"]
    assert right.azimuth_rad == pytest.approx(-0.3, abs=0.08)


@pytest.mark.parametrize(
    ("xy", "why"),
    [
        (ahead(2.0, 1.0), "outside hfov (1.0 > 0.785 rad)"),
        (ahead(2.0, -1.0), "outside hfov on the right"),
        ((1.96, -1.45 + 8.5), "beyond max range"),
        ((1.96, -2.5), "behind the radar"),
        ((1.96, -0.6), "too close: below the vertical beam"),
    ],
)
def test_field_of_view_and_range(sim: RadarSimulator, xy: tuple[float, float], why: str) -> None:
    sim.model = sim.model.model_copy(update={"occlusion_max_fraction": 1.0})  # geometry only
    assert scan(sim, [state("a", xy)]) == [], why
    assert by_vehicle(scan(sim, [state("a", xy), state("ok", ahead(2.0, 0.45))])).keys() == {"ok"}


def test_vehicle_behind_vehicle_is_dropped(sim: RadarSimulator) -> None:
    near, far = state("near", ahead(1.3, 0.45)), state("far", ahead(2.3, 0.45))
    assert by_vehicle(scan(sim, [far])).keys() == {"far"}  # clear line of sight alone
    assert by_vehicle(scan(sim, [near, far])).keys() == {"near"}
    assert sim.blocked_fractions([near, far])["far"] > sim.model.occlusion_max_fraction
    # Order does not matter, and the occluder itself is not blocked by the vehicle behind it.
    assert by_vehicle(scan(sim, [far, near])).keys() == {"near"}


def test_vehicle_behind_building_is_dropped(sim: RadarSimulator) -> None:
    hidden = state("hidden", (2.6, 0.9))  # north of building_e as seen from radar_3
    fractions = sim.blocked_fractions([hidden])
    assert fractions["hidden"] > 0.99  # in the field of view, but blocked
    assert scan(sim, [hidden]) == []
    sim.model = sim.model.model_copy(update={"occlusion_max_fraction": 1.0})
    assert by_vehicle(scan(sim, [hidden])).keys() == {"hidden"}


def test_clutter_rate_and_flags(sim: RadarSimulator) -> None:
    rate = 3.0
    sim.model = sim.model.model_copy(update={"clutter_per_scan": rate})
    m = sim.model
    counts = []
    for seed in range(400):
        targets = scan(sim, [], seed)
        counts.append(len(targets))
        for i, t in enumerate(targets):
            assert t.is_clutter and t.vehicle_id == "" and t.target_index == i
            assert m.min_range_m <= t.range_m <= m.max_range_m
            assert abs(t.azimuth_rad) <= m.hfov_rad / 2 and abs(t.elevation_rad) <= m.vfov_rad / 2
        assert [t.range_m for t in targets] == sorted(t.range_m for t in targets)
    assert np.mean(counts) == pytest.approx(rate, abs=0.3)


def test_max_targets_cap(sim: RadarSimulator) -> None:
    sim.model = sim.model.model_copy(update={"clutter_per_scan": 30.0, "max_targets": 5})
    targets = scan(sim, [state("a", ahead(2.0, 0.45))], seed=3)
    assert len(targets) == 5
    assert [t.target_index for t in targets] == list(range(5))


def test_detection_probability_zero(sim: RadarSimulator) -> None:
    sim.model = sim.model.model_copy(update={"detection_probability": 0.0})
    assert scan(sim, [state("a", ahead(2.0, 0.45))]) == []


def test_same_seed_same_targets(scene: Scene, worlds: tuple[StaticWorld, VehicleWorld]) -> None:
    radar = RadarSimulator(scene, RADAR, *worlds)  # the scene's noisy model, with clutter
    states = [
        state("a", ahead(2.0, 0.45), v=(0.1, -0.3, 0)),
        state("b", (1.96, 0.3), v=(0, -0.5, 0)),
        state("c", ahead(3.0, 0.2)),
    ]
    first = scan(radar, states, seed=7)
    assert len(by_vehicle(first)) >= 2
    assert scan(radar, states, seed=7) == first
    assert scan(radar, states, seed=8) != first


def test_to_radar_scan(sim: RadarSimulator) -> None:
    sim.model = sim.model.model_copy(update={"clutter_per_scan": 2.0})
    targets = scan(sim, [state("a", ahead(2.0, 0.45), v=(0, -0.2, 0))], seed=1)
    msg = to_radar_scan(targets, RADAR)
    assert msg.sensor_id == RADAR and not msg.HasField("header")
    assert len(msg.targets) == len(targets)
    for i, (t, pb_t) in enumerate(zip(targets, msg.targets, strict=True)):
        assert pb_t.target_index == i
        assert pb_t.range_m == t.range_m and pb_t.azimuth_rad == t.azimuth_rad
        assert pb_t.elevation_rad == t.elevation_rad and pb_t.range_rate_mps == t.range_rate_mps
        assert pb_t.rcs_dbsm == t.rcs_dbsm and pb_t.snr_db == t.snr_db
        assert pb_t.is_clutter == t.is_clutter

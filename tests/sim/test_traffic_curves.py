"""Vehicles slow for bends (TrafficSettings.curve_lateral_accel_mps2): a known bend, the real-size
intersection with its mix of classes, and the sand table left as it was."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.scene.road_network import Path, RoadNetwork
from shared.scene.scene import Scene
from shared.supervision.profiles import scene_profile
from sim.config import TrafficSettings, load_sim_settings
from sim.traffic import TrafficSim, Vehicle
from tests.helpers import FULL_SCALE_SCENE

# Pure pursuit overshoots the path's curvature for a moment where it enters a bend (measured: 5 % on
# the intersection's turns and ring corners).
LATERAL_TOLERANCE = 0.1
SECONDS = 60.0
STEP_M = 0.05  # sampling of the test bend, finer than the scene's lanes: its curvature is exact


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.load(FULL_SCALE_SCENE)


@pytest.fixture(scope="module")
def limit_mps2() -> float:
    """The intersection's limit, from its profile (the one home of the value)."""
    value = scene_profile("intersection").overrides["sim"]["traffic"]["curve_lateral_accel_mps2"]
    return float(value)


def right_bend(radius_m: float, straight_m: float) -> Path:
    """Eastward `straight_m`, a quarter circle of `radius_m` to the right, southward `straight_m`."""
    approach = np.arange(0.0, straight_m, STEP_M)
    angles = np.arange(0.0, math.pi / 2, STEP_M / radius_m)
    leave = np.arange(0.0, straight_m + STEP_M / 2, STEP_M)
    xy = np.concatenate(
        [
            np.column_stack([approach - straight_m, np.zeros_like(approach)]),
            np.column_stack([radius_m * np.sin(angles), radius_m * (np.cos(angles) - 1)]),
            np.column_stack([np.full_like(leave, radius_m), -radius_m - leave]),
        ]
    )
    return Path("bend", np.column_stack([xy, np.zeros(len(xy))]), lane_id="e_in")


def drive_through(scene: Scene, radius_m: float, limit_mps2: float | None) -> dict[str, np.ndarray]:
    """One car, alone, from its lane's speed limit through `right_bend(radius_m)`: per tick its progress,
    speed, lateral acceleration and deceleration (the sim's own controller, `TrafficSim._drive`)."""
    settings = load_sim_settings(
        scene=str(FULL_SCALE_SCENE), vehicles=0, traffic={"curve_lateral_accel_mps2": limit_mps2}
    )
    traffic = TrafficSim(scene, RoadNetwork(scene), settings.traffic, settings.seed, settings.tick_hz)
    path = right_bend(radius_m, straight_m=60.0)
    # The lane gives the bend its speed limit (13.9 m/s, an arm of the crossing).
    v0 = traffic._speed_limit(path)
    car = Vehicle("v00", 0, (1.0, 1.0, 1.0, 1.0), scene.spec.vehicle, path, 0.0, -60.0, 0.0, 0.0, 0.0, v=v0)
    car.lane_id = "e_in"
    rows = []
    bend_end_m = 60.0 + radius_m * math.pi / 2
    while car.s < bend_end_m:
        v_before = car.v
        traffic._drive(car, {})
        rows.append((car.s, car.v, abs(car.v * car.yaw_rate), (v_before - car.v) * settings.tick_hz))
    s, v, lateral, decel = np.array(rows).T
    pursuit, comfort = traffic.cfg.pursuit, traffic.cfg.idm.comfort_decel_mps2
    return {
        "s_m": s - 60.0,
        "v_mps": v,
        "lateral_mps2": lateral,
        "decel_mps2": decel,
        "v0_mps": np.array(v0),
        "comfort_decel_mps2": np.array(comfort),
        "lookahead": np.array([pursuit.lookahead_min_m, pursuit.lookahead_gain_s]),
    }


@pytest.mark.parametrize("radius_m", [10.0, 20.0])
def test_a_bend_of_known_radius_is_taken_at_its_speed(
    scene: Scene, limit_mps2: float, radius_m: float
) -> None:
    run = drive_through(scene, radius_m, limit_mps2)
    bend_speed_mps = math.sqrt(limit_mps2 * radius_m)  # 5.5 and 7.7 m/s at 3 m/s2
    assert run["v0_mps"] > 1.5 * bend_speed_mps  # the approach is fast: the car has to slow
    # The car speeds up once its pursuit target, a look-ahead ahead, has left the bend: held to the
    # bend's speed until half its look-ahead before the bend's end.
    lookahead_min_m, gain_s = run["lookahead"]
    exit_m = radius_m * math.pi / 2 - (lookahead_min_m + gain_s * bend_speed_mps) / 2
    in_bend = (run["s_m"] >= 0.0) & (run["s_m"] <= exit_m)
    # Slowed before the bend, not inside it: at the speed on entry and throughout.
    assert run["v_mps"][in_bend].max() <= bend_speed_mps * 1.01
    assert run["lateral_mps2"].max() <= limit_mps2 * (1 + LATERAL_TOLERANCE)
    # ... at the IDM's comfortable deceleration (scaled to the intersection: 4.17 m/s2).
    assert run["decel_mps2"].max() <= run["comfort_decel_mps2"] * 1.01
    # Not crawling: it keeps the bend's speed rather than far below it.
    assert run["v_mps"][in_bend].min() >= 0.9 * bend_speed_mps


def test_without_the_limit_the_bend_is_taken_at_the_lane_speed(scene: Scene) -> None:
    run = drive_through(scene, 10.0, None)
    assert run["v_mps"][run["s_m"] >= 0.0].min() > 0.95 * run["v0_mps"]
    assert run["lateral_mps2"].max() > 10.0  # 13.9 m/s on 10 m: ~19 m/s2 where the car can follow


@pytest.mark.parametrize("seed", [101, 102])
def test_the_intersection_fleet_keeps_within_the_limit(scene: Scene, limit_mps2: float, seed: int) -> None:
    """Cars, vans and trucks (the scene's mix), 12 vehicles, 60 s: every vehicle's lateral acceleration
    within the limit, no overlaps, trips completed."""
    settings = load_sim_settings(
        scene=str(FULL_SCALE_SCENE), seed=seed, vehicles=12, traffic={"curve_lateral_accel_mps2": limit_mps2}
    )
    traffic = TrafficSim(scene, RoadNetwork(scene), settings.traffic, settings.seed, settings.tick_hz)
    assert {v.body.name for v in traffic.vehicles} == {"car", "van", "truck"}
    lateral = dict.fromkeys((v.id for v in traffic.vehicles), 0.0)
    for _ in range(round(SECONDS * settings.tick_hz)):
        traffic.step()
        assert not traffic.overlapping_pairs()
        for v in traffic.vehicles:
            lateral[v.id] = max(lateral[v.id], abs(v.v * v.yaw_rate))
    assert max(lateral.values()) <= limit_mps2 * (1 + LATERAL_TOLERANCE), lateral
    assert traffic.trips_completed >= 4  # measured 9 and 5 (without the limit 9 and 8)


def test_off_by_default_and_on_the_sand_table(scene: Scene, table_scene: Scene) -> None:
    assert TrafficSettings().curve_lateral_accel_mps2 is None
    assert load_sim_settings().traffic.curve_lateral_accel_mps2 is None  # the table's sim settings
    table_overrides = scene_profile("sand_table").overrides.get("sim", {}).get("traffic", {})
    assert "curve_lateral_accel_mps2" not in table_overrides
    for s in (table_scene, scene):
        traffic = TrafficSim(s, RoadNetwork(s), TrafficSettings(vehicles=1), 1, 60.0)
        assert traffic.cfg.curve_lateral_accel_mps2 is None  # not scaled into existence

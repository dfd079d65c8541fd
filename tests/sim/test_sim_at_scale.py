"""The simulator at the scene's scale: traffic, worlds, the board session and the bird's-eye map built for
the sand table run their defaults as written (bit for bit); built for the real-size intersection, every
size, speed and acceleration is the scene's, and its traffic drives at real speeds without collisions."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from pydantic import BaseModel

from shared.config import read_yaml, with_overrides
from shared.scene.model import LEVEL_SEPARATION_M
from shared.scene.road_network import RoadNetwork
from shared.scene.scale import Scales, SiteScale, at_scale, scaled_fields
from shared.scene.scene import Scene
from sim.config import (
    DEFAULT_SIM_CONFIG,
    BirdsEyeSettings,
    BoardSessionSettings,
    SimSettings,
    TrafficSettings,
    WorldSettings,
)
from sim.sensors.board import board_session
from sim.traffic import TrafficSim
from sim.world import StaticWorld, VehicleWorld, world_settings
from tests.test_any_scale import undeclared_unit_fields

TICK_HZ = 60.0


def assert_real_size(at_table: BaseModel, at_full: BaseModel, scale: SiteScale) -> None:
    """Every scaled setting of `at_full` differs from `at_table`'s by exactly its kind's factor."""
    table_values, full_values = scaled_fields(at_table), scaled_fields(at_full)
    assert full_values.keys() == table_values.keys() and full_values
    for path, (marker, value) in full_values.items():
        assert isinstance(marker, Scales)
        reference = table_values[path][1]
        if reference is None and value is None:
            continue  # an optional size left unset (off) has no value to scale
        assert value != reference, path
        expected = np.asarray(reference) * scale.factor(marker)
        assert np.asarray(value) == pytest.approx(expected), path


@pytest.mark.parametrize(
    "root", [SimSettings, BoardSessionSettings, BirdsEyeSettings], ids=lambda r: r.__name__
)
def test_every_size_setting_says_how_it_scales(root: type[BaseModel]) -> None:
    assert undeclared_unit_fields(root) == []


def test_the_base_settings_file_gives_no_size() -> None:
    # A size in the base file would be used as written at every scale: sizes belong in a site's profile.
    explicit = SimSettings.model_validate(read_yaml(DEFAULT_SIM_CONFIG))
    given = [path for path in scaled_fields(explicit) if _is_set(explicit, path.split("."))]
    assert given == []


# --- traffic -------------------------------------------------------------------------------------


def traffic(scene: Scene, settings: TrafficSettings | None = None, vehicles: int = 6) -> TrafficSim:
    cfg = settings or TrafficSettings(vehicles=vehicles)
    return TrafficSim(scene, RoadNetwork(scene), cfg, seed=1, tick_hz=TICK_HZ)


def test_the_table_traffic_runs_the_defaults_as_written(table_scene: Scene) -> None:
    cfg = traffic(table_scene).cfg
    assert scaled_fields(cfg) == scaled_fields(TrafficSettings())
    assert cfg.level_separation_m == LEVEL_SEPARATION_M and cfg.idm.max_accel_mps2 == 0.6


def test_the_real_size_traffic_keeps_no_table_value(table_scene: Scene, full_scene: Scene) -> None:
    at_full = traffic(full_scene).cfg
    assert_real_size(traffic(table_scene).cfg, at_full, SiteScale.of(full_scene.spec))
    # The car's own acceleration, the site's top speed.
    assert at_full.idm.max_accel_mps2 == pytest.approx(full_scene.spec.vehicle.max_accel_mps2)
    assert at_full.max_speed_mps == pytest.approx(full_scene.spec.top_speed_mps)


def test_a_size_given_explicitly_is_taken_as_written(full_scene: Scene) -> None:
    cfg = traffic(full_scene, TrafficSettings.model_validate({"vehicles": 2, "idm": {"min_gap_m": 2.0}})).cfg
    assert cfg.idm.min_gap_m == 2.0
    assert cfg.idm.max_accel_mps2 == pytest.approx(2.5)  # the rest still scaled
    # Overridden in code as the flow experiment does (shared.config.with_overrides): still scaled.
    overridden = traffic(
        full_scene, with_overrides(TrafficSettings(), {"vehicles": 2, "route_policy": "plan"})
    ).cfg
    assert overridden.idm.min_gap_m == pytest.approx(0.1 * SiteScale.of(full_scene.spec).length)


def test_the_real_size_traffic_drives_at_real_speeds_without_collisions(full_scene: Scene) -> None:
    sim = traffic(full_scene, vehicles=10)
    speeds = []
    for tick in range(round(40 * TICK_HZ)):
        sim.step()
        if tick % 30 == 0:
            assert sim.overlapping_pairs() == []
            speeds.append(np.mean([v.v for v in sim.vehicles]))
    assert np.mean(speeds) > 4.0  # m/s: a table-sized car-following would crawl or stall
    assert sum(sim.arrivals.values()) >= 10  # through the junctions, not gridlocked at the first


# --- worlds, board session, bird's-eye map -------------------------------------------------------


@pytest.fixture(scope="module")
def worlds(full_scene: Scene) -> Iterator[tuple[StaticWorld, VehicleWorld]]:
    static = StaticWorld(full_scene)
    vehicles = VehicleWorld(full_scene, settings=static.settings)
    yield static, vehicles
    vehicles.close()
    static.close()


def test_the_table_worlds_run_the_defaults_as_written(table_scene: Scene, static: StaticWorld) -> None:
    assert scaled_fields(static.settings) == scaled_fields(WorldSettings())
    assert scaled_fields(board_session(table_scene)) == scaled_fields(BoardSessionSettings())
    drawing = at_scale(BirdsEyeSettings(), SiteScale.of(table_scene.spec))
    assert scaled_fields(drawing) == scaled_fields(BirdsEyeSettings())


def test_the_real_size_worlds_keep_no_table_value(
    table_scene: Scene, full_scene: Scene, worlds: tuple[StaticWorld, VehicleWorld]
) -> None:
    scale = SiteScale.of(full_scene.spec)
    static, vehicles = worlds
    assert_real_size(world_settings(table_scene), static.settings, scale)
    assert vehicles.settings == static.settings
    assert_real_size(board_session(table_scene), board_session(full_scene), scale)
    assert_real_size(
        at_scale(BirdsEyeSettings(), SiteScale.of(table_scene.spec)),
        at_scale(BirdsEyeSettings(), scale),
        scale,
    )
    # The road texture has the table's resolution in pixels per car length, not per metre.
    assert static.settings.texture_px_per_m * full_scene.spec.vehicle.length_m == pytest.approx(128 * 0.33)


def test_the_real_size_world_stands_on_its_table(worlds: tuple[StaticWorld, VehicleWorld]) -> None:
    import pybullet as pb

    static, _ = worlds
    hit = pb.rayTest([0.0, 0.0, 50.0], [0.0, 0.0, -50.0], physicsClientId=static.cid)[0]
    assert static.body_kind.get(hit[0]) == "table"
    top_z = 50.0 - 100.0 * hit[2]
    assert top_z == pytest.approx(-static.settings.table_slab_drop_m)


def _is_set(model: object, path: list[str]) -> bool:
    head, *rest = path
    if head not in getattr(model, "model_fields_set", set()):
        return False
    return not rest or _is_set(getattr(model, head), rest)

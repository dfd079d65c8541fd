"""The coordinator at the scene's scale: built for the sand table its settings are the defaults as written
(bit for bit), built for the real-size intersection every size and speed is the scene's; a scene without
a lane map is refused by name."""

from __future__ import annotations

import pytest

from shared.config import ConfigError, read_yaml
from shared.scene.model import SceneSpec
from shared.scene.scale import SPEED, Scales, SiteScale, scaled_fields
from shared.scene.scene import Scene
from shared.traffic.config import DEFAULT_COORDINATOR_CONFIG, CoordinatorSettings, load_coordinator_settings
from shared.traffic.core import CoordinatorCore
from shared.traffic.lanes import lane_network
from tests.helpers import FULL_SCALE_SCENE
from tests.test_any_scale import undeclared_unit_fields


def test_every_size_setting_says_how_it_scales() -> None:
    assert undeclared_unit_fields(CoordinatorSettings) == []


def test_the_table_core_runs_the_defaults_as_written(table_scene: Scene) -> None:
    settings = load_coordinator_settings()
    core = CoordinatorCore(table_scene, settings, 16)
    assert scaled_fields(core.settings) == scaled_fields(settings)
    assert core.settings.maps.grid_cell_m == 0.25 and core.settings.maps.dedup_gate_m == 0.3


@pytest.mark.parametrize(
    "settings", [CoordinatorSettings(), load_coordinator_settings()], ids=["code", "base_file"]
)
def test_the_real_size_core_keeps_no_table_value(
    table_scene: Scene, full_scene: Scene, settings: CoordinatorSettings
) -> None:
    at_table = scaled_fields(CoordinatorCore(table_scene, settings, 16).settings)
    at_full = scaled_fields(CoordinatorCore(full_scene, settings, 16).settings)
    assert at_full.keys() == at_table.keys() and len(at_full) >= 6
    scale = SiteScale.of(full_scene.spec)
    for path, (marker, value) in at_full.items():
        assert isinstance(marker, Scales)
        assert value != at_table[path][1], path
        assert value == pytest.approx(at_table[path][1] * scale.factor(marker)), path
    # Real sizes: two agents' views of one car merge across half a car length, not 0.3 m.
    maps = CoordinatorCore(full_scene, settings, 16).settings.maps
    assert maps.dedup_gate_m == pytest.approx(0.3 * full_scene.spec.vehicle.length_m / 0.33)
    assert at_full["planner.min_speed_mps"] == (
        SPEED,
        pytest.approx(0.05 * full_scene.spec.top_speed_mps / 0.5),
    )


def test_a_size_given_explicitly_is_taken_as_written(full_scene: Scene) -> None:
    settings = CoordinatorSettings.model_validate({"maps": {"grid_cell_m": 2.0}})
    maps = CoordinatorCore(full_scene, settings, 16).settings.maps
    assert maps.grid_cell_m == 2.0
    assert maps.dedup_gate_m > 4.0  # the rest still scaled


def test_the_base_settings_file_gives_no_size() -> None:
    # A size in the base file would be used as written at every scale: sizes belong in a site's profile.
    explicit = CoordinatorSettings.model_validate(read_yaml(DEFAULT_COORDINATOR_CONFIG))
    given = [path for path in scaled_fields(explicit) if _is_set(explicit, path.split("."))]
    assert given == []


def test_a_scene_without_lanes_is_refused_by_name(full_scene: Scene) -> None:
    data = full_scene.spec.model_dump()
    data.update(scene_id="bare_site", lanes=[], junctions=[], road=None, design_speed_mps=13.9)
    bare = Scene(SceneSpec.model_validate(data), source=FULL_SCALE_SCENE.with_name("bare_site.yaml"))
    for build in (lambda: lane_network(bare), lambda: CoordinatorCore(bare, CoordinatorSettings(), 16)):
        with pytest.raises(ConfigError, match=r"scene bare_site \(.*bare_site.yaml\) has no lane map") as err:
            build()
        assert "the coordinator needs one" in str(err.value)
    # A road block without lanes is no lane map either.
    data.update(road=full_scene.spec.road.model_dump() if full_scene.spec.road is not None else None)
    with pytest.raises(ConfigError, match="has no lane map"):
        CoordinatorCore(Scene(SceneSpec.model_validate(data)), CoordinatorSettings(), 16)


def _is_set(model: object, path: list[str]) -> bool:
    head, *rest = path
    if head not in getattr(model, "model_fields_set", set()):
        return False
    return not rest or _is_set(getattr(model, head), rest)

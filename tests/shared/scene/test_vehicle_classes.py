"""Vehicle classes and the traffic mix of a scene: optional (the reference `vehicle` alone is a fleet of
one class), each class its own size, fractions validated with a message that says what is wrong."""

from __future__ import annotations

from typing import Any

import pytest
import yaml

from shared.paths import DEFAULT_SCENE
from shared.scene.model import SceneSpec
from shared.scene.scale import SiteScale
from shared.scene.scene import Scene

VAN = {"name": "van", "length_m": 4.9, "width_m": 1.9, "height_m": 2.0, "wheelbase_m": 3.0}
TRUCK = {
    "name": "truck",
    "label": "truck",
    "length_m": 8.5,
    "width_m": 2.5,
    "height_m": 3.2,
    "wheelbase_m": 4.5,
}


def _table_raw() -> dict[str, Any]:
    return yaml.safe_load(DEFAULT_SCENE.read_text())


def _with_classes(mix: dict[str, float] | None) -> dict[str, Any]:
    data = _table_raw()
    drive = {"max_steer_rad": 0.6, "max_accel_mps2": 1.0}
    data["vehicle_classes"] = [{**VAN, **drive}, {**TRUCK, **drive}]
    if mix is not None:
        data["traffic_mix"] = mix
    return data


def test_classes_are_optional_the_sand_table_is_one_reference_class(table_scene: Scene) -> None:
    spec = table_scene.spec
    assert spec.vehicle_classes == [] and spec.traffic_mix is None
    assert spec.fleet_mix == [(spec.vehicle, 1.0)]
    assert (spec.vehicle.name, spec.vehicle.label) == ("car", "car")  # the defaults: the file names none
    assert spec.vehicle_class("car") is spec.vehicle


def test_a_mix_lists_each_class_with_its_own_size() -> None:
    spec = SceneSpec.model_validate(_with_classes({"car": 0.5, "van": 0.3, "truck": 0.2}))
    assert [(c.name, f) for c, f in spec.fleet_mix] == [("car", 0.5), ("van", 0.3), ("truck", 0.2)]
    assert spec.vehicle_class("truck").size_m == (8.5, 2.5, 3.2)
    assert spec.vehicle_class("truck").label == "truck" and spec.vehicle_class("van").label == "car"
    with pytest.raises(KeyError, match="bus"):
        spec.vehicle_class("bus")
    # A class at fraction 0 is listed but never spawned.
    spec = SceneSpec.model_validate(_with_classes({"car": 0.0, "van": 0.5, "truck": 0.5}))
    assert [c.name for c, _ in spec.fleet_mix] == ["van", "truck"]


def test_the_scale_stays_the_reference_vehicles() -> None:
    plain = SceneSpec.model_validate(_table_raw())
    mixed = SceneSpec.model_validate(_with_classes({"car": 0.5, "van": 0.3, "truck": 0.2}))
    assert SiteScale.of(mixed) == SiteScale.of(plain)


def test_the_intersection_mixes_cars_vans_and_trucks(full_scene: Scene) -> None:
    mix = {c.name: (f, c.size_m) for c, f in full_scene.spec.fleet_mix}
    assert mix == {
        "car": (0.7, (4.5, 1.8, 1.5)),
        "van": (0.2, (4.9, 1.9, 2.0)),
        "truck": (0.1, (8.5, 2.5, 3.2)),
    }
    assert full_scene.spec.vehicle.name == "car"  # the reference class: the scale is unchanged
    assert SiteScale.of(full_scene.spec).length == pytest.approx(4.5 / 0.33)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (_with_classes(None), r"vehicle_classes \['van', 'truck'\] given without a traffic_mix"),
        (_with_classes({"car": 0.5, "van": 0.3, "truck": 0.3}), "must sum to 1, they sum to 1.1"),
        (_with_classes({"car": 0.5, "van": 0.3}), "must sum to 1, they sum to 0.8"),
        (_with_classes({"car": 0.5, "van": 0.3, "bus": 0.2}), r"unknown vehicle classes \['bus'\]"),
        (_with_classes({"car": 1.2, "van": -0.2}), r"must lie in \[0, 1\]"),
        (_with_classes({"car": float("nan"), "van": 1.0}), r"must lie in \[0, 1\]"),
        ({**_table_raw(), "traffic_mix": {"car": 1.0, "van": 0.0}}, r"unknown vehicle classes \['van'\]"),
    ],
    ids=["no-mix", "sum-over", "sum-under", "unknown", "out-of-range", "nan", "class-not-listed"],
)
def test_a_bad_mix_is_rejected_with_a_clear_message(data: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        SceneSpec.model_validate(data)


def test_class_names_are_unique_the_reference_included() -> None:
    data = _with_classes({"car": 0.5, "van": 0.5})
    data["vehicle_classes"][1]["name"] = "car"
    with pytest.raises(ValueError, match=r"duplicate vehicle class names .*\['car'\]"):
        SceneSpec.model_validate(data)
    data = _with_classes({"car": 0.5, "van": 0.5})
    data["vehicle_classes"][1]["label"] = "lorry"
    with pytest.raises(ValueError, match="label"):
        SceneSpec.model_validate(data)

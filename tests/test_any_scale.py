"""Scale comes from the scene (issue 49 item 1): every core built for the sand table and for a real-size
scene, and no parameter of the real-size core still has its table value.

Three checks, each shown to fail on a planted table-sized default:
- every settings field with a unit of size in its name (``_m``, ``_mps``, ``_mps2``, ``_m2``,
  ``_per_m``, ...) says how it scales (shared/scene/scale.py) or is read from the scene;
- no module of the perception, detection, tracking, coordinator or simulator packages keeps a constant
  with such a unit, other than the numerical guards and device facts named here with their reasons;
- the cores built for the real-size intersection differ from the table's in every scaled or scene-read
  setting.
"""

from __future__ import annotations

import re
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pydantic import BaseModel, Field

from shared.config import with_overrides
from shared.detection.lidar.pointpillars.config import PointPillarsConfig
from shared.detection.oracle import OracleCameraDetector, OracleLidarDetector
from shared.paths import REPO_ROOT
from shared.perception.config import MecSettings
from shared.perception.core import MecCore
from shared.scene.scale import Scales, SiteScale, at_scale, scaled_fields, scales_of
from shared.scene.scene import Scene
from shared.traffic.config import CoordinatorSettings
from sim.config import SimSettings

UNIT = re.compile(r"_(m|mps|mps2|m2|m2ps2|per_m|per_m2|px_m)$")

# Module constants with a unit of size that do not scale, and why.
NOT_SITE_SIZES = {
    "NEAR_M": "numerical slack of k-d tree radii (1e-6)",
    "_MIN_RANGE_M": "guards a division at the sensor's own position (1e-6)",
    "_DEGENERATE_AREA_M2": "numerical guard of a plane fit (1e-9)",
    "DISTANCE_RES_M": "the Robosense protocol's range unit (a device fact)",
    "DISTANCE_UNIT_M": "the Velodyne protocol's range unit (a device fact)",
    "LEVEL_SEPARATION_M": "the reference value of scaled Length settings (their default)",
}
CONSTANT_PACKAGES = (
    "shared/perception",
    "shared/detection",
    "shared/tracking",
    "shared/traffic",
    "shared/scene/road_network.py",
    "shared/scene/model.py",
    "sim",
    "services/mec",
    "services/coordinator",
    "services/sim",
)
# The SUMO bridge keeps its networks at 1:18 on purpose (TABLE_SCALE): the city study's scenes.
CONSTANT_EXCLUDED = ("sim/sumo",)
CONSTANT = re.compile(r"^(?P<name>_?[A-Z][A-Z0-9_]*_(M|MPS|MPS2|M2|PER_M))\s*(:[^=]+)?=", re.MULTILINE)


def model_types(annotation: Any) -> Iterator[type[BaseModel]]:
    """The pydantic models inside a field's annotation (`X`, `X | None`, `Annotated[X, ...]`)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        yield annotation
    for arg in typing.get_args(annotation):
        yield from model_types(arg)


def undeclared_unit_fields(model: type[BaseModel], prefix: str = "") -> list[str]:
    """Fields of `model` (nested models too) whose name carries a unit of size but whose type says
    neither how they scale nor that the scene sets them."""
    out = []
    for name, info in model.model_fields.items():
        nested = list(model_types(info.annotation))
        if nested:
            for sub in nested:
                out += undeclared_unit_fields(sub, f"{prefix}{name}.")
            continue
        if UNIT.search(name) and scales_of(info.metadata) is None:
            out.append(f"{prefix}{name}")
    return out


def table_sized(full: BaseModel, table: BaseModel) -> list[str]:
    """Scaled or scene-read settings of `full` that still have the value they have in `table`
    (zeros, which every scale keeps, aside)."""
    table_values = scaled_fields(table)
    out = []
    for path, (marker, value) in scaled_fields(full).items():
        reference = table_values[path][1]
        if reference is None or not any(reference if isinstance(reference, tuple) else (reference,)):
            continue
        scale_free = isinstance(marker, Scales) and marker == Scales(marker.kind)  # a ratio
        if not scale_free and value == reference:
            out.append(f"{path} = {value}")
    return out


def module_constants(paths: list[Path]) -> list[str]:
    """`path: NAME` of every module-level constant with a unit of size, less the ones named above."""
    out = []
    for path in paths:
        for match in CONSTANT.finditer(path.read_text()):
            if match["name"] not in NOT_SITE_SIZES:
                where = path.relative_to(REPO_ROOT) if path.is_relative_to(REPO_ROOT) else path
                out.append(f"{where}: {match['name']}")
    return out


def mec_settings(scene: Scene, agent_id: str, settings: MecSettings | None = None) -> MecSettings:
    """The settings a MecCore for `agent_id` of `scene` runs with (oracle detectors: no model files)."""
    core = MecCore(
        scene,
        agent_id,
        settings or MecSettings(),
        cameras=OracleCameraDetector(seed=0),
        lidar=OracleLidarDetector(seed=0),
    )
    return core.settings


# --- the scale itself ---------------------------------------------------------------------------


def test_the_table_is_the_reference_and_the_intersection_is_real_size(
    table_scene: Scene, full_scene: Scene
) -> None:
    assert SiteScale.of(table_scene.spec) == SiteScale(1.0, 1.0, 1.0)
    scale = SiteScale.of(full_scene.spec)
    assert scale.length > 10 and scale.speed > 10 and scale.accel > 2


# --- every unit field declares how it scales ------------------------------------------------------


# PointPillarsConfig: a trained model's is explicit; the defaults a model to be trained starts from scale.
CONFIG_ROOTS: tuple[type[BaseModel], ...] = (
    MecSettings,
    CoordinatorSettings,
    SimSettings,
    PointPillarsConfig,
)


@pytest.mark.parametrize("root", CONFIG_ROOTS, ids=lambda r: r.__name__)
def test_every_size_setting_says_how_it_scales(root: type[BaseModel]) -> None:
    assert undeclared_unit_fields(root) == []


def test_pointpillars_to_be_trained_at_real_size_keeps_no_table_length(full_scene: Scene) -> None:
    table = PointPillarsConfig()
    full = at_scale(table, SiteScale.of(full_scene.spec))
    assert table_sized(full, table) == []
    checked = PointPillarsConfig.model_validate(full.model_dump())  # the scaled grid is a valid grid
    assert (checked.grid.nx, checked.train_grid().nx) == (table.grid.nx, table.train_grid().nx)


def test_an_undeclared_size_setting_is_found() -> None:
    class Planted(BaseModel):
        gate_m: float = Field(0.5)  # a table-sized gate that says nothing of its scale

    class Holder(BaseModel):
        tracker: Planted = Planted()
        count: int = 3

    assert undeclared_unit_fields(Holder) == ["tracker.gate_m"]


def test_no_module_keeps_a_size_constant() -> None:
    files = [
        p
        for pkg in CONSTANT_PACKAGES
        for p in sorted((REPO_ROOT / pkg).rglob("*.py") if (REPO_ROOT / pkg).is_dir() else [REPO_ROOT / pkg])
        if not any(p.is_relative_to(REPO_ROOT / x) for x in CONSTANT_EXCLUDED)
    ]
    assert module_constants(files) == []


def test_a_planted_size_constant_is_found(tmp_path: Path) -> None:
    planted = tmp_path / "planted.py"
    planted.write_text("NEAR_M = 1e-6\nGATE_M = 0.5\nLIMIT_MPS: float = 0.5\n")
    assert [line.split(": ")[1] for line in module_constants([planted])] == ["GATE_M", "LIMIT_MPS"]


# --- the cores at 1:1 --------------------------------------------------------------------------------


def test_the_mec_at_real_size_keeps_no_table_value(table_scene: Scene, full_scene: Scene) -> None:
    full_agent = full_scene.spec.agents[0].id
    table_agent = next(a.id for a in table_scene.spec.agents if table_scene.sensors_of(a.id, "lidar"))
    at_full = mec_settings(full_scene, full_agent)
    assert table_sized(at_full, mec_settings(table_scene, table_agent)) == []
    # The real-size core really is real-size: the tracker's gate holds a car's 10 Hz step at 50 km/h.
    assert at_full.tracker.gate_m > 13.9 / 10
    assert at_full.detectors.cluster.vehicle_size_m == full_scene.spec.vehicle.size_m


def test_a_table_value_given_to_the_real_size_mec_is_found(table_scene: Scene, full_scene: Scene) -> None:
    planted = with_overrides(MecSettings(), {"tracker": {"gate_m": 0.5}})  # the table's gate, by hand
    at_full = mec_settings(full_scene, full_scene.spec.agents[0].id, planted)
    table_agent = next(a.id for a in table_scene.spec.agents if table_scene.sensors_of(a.id, "lidar"))
    assert table_sized(at_full, mec_settings(table_scene, table_agent)) == ["tracker.gate_m = 0.5"]


def test_the_base_settings_files_give_no_size(table_scene: Scene) -> None:
    # A size in a base file would be taken as written at every scale: sizes belong in a site's profile.
    from shared.config import read_yaml
    from shared.perception.config import DEFAULT_MEC_CONFIG

    explicit = MecSettings.model_validate(read_yaml(DEFAULT_MEC_CONFIG))
    given = {path for path in scaled_fields(explicit) if _is_set(explicit, path.split("."))}
    assert given == set()


def _is_set(model: BaseModel, path: list[str]) -> bool:
    head, *rest = path
    if head not in model.model_fields_set:
        return False
    return not rest or _is_set(getattr(model, head), rest)

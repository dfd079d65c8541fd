"""Which quantities scale how: the one place that says it.

A site is described by its scene (vehicles, lanes, sensors), at any size: the paper's 1:18 sand table,
a real intersection. A setting that is a size, a distance, a speed, a gate or a noise level carries
its *kind* in its type, and its default is stated for the reference site the project was tuned on
(the sand table). Built for another scene (`at_scale`), every such setting left at its default is
multiplied by the factor of its kind for that scene; a setting given explicitly (a profile's settings
file, an environment override, a constructor argument) is taken as written, in the scene's own units.

Kinds and their factors, with ``L`` = scene length / reference length, ``V`` = scene speed /
reference speed and ``A`` = scene acceleration / reference acceleration (`SiteScale.of`):

========================  =========  ==========================================================
kind                      factor     examples
========================  =========  ==========================================================
``Length`` (m)            L          gates, radii, clustering distances, position noise, grid cells
``Area`` (m²)             L²         position variances
``PerLength`` (1/m)       1 / L      a radius that grows with the square of the range, per m²
``Speed`` (m/s)           V          velocity noise, speed thresholds
``Ratio`` (m/m, ...)      1          a length per length (a radius that grows with range):
                                     named in a unit of size, but scale-free
``Acceleration`` (m/s²)   A          process noise, car-following accelerations (no power of
                                     L and V fits: a DeepRacer reaches 1.5 lengths/s at 0.6 m/s²,
                                     a car 3 lengths/s at ~2.5 m/s²; the vehicle says it)
``FromScene``             --         not a default at all: the builder reads it from the scene
                                     (vehicle size, sensor range, sensor positions)
========================  =========  ==========================================================

Unscaled, and so plain ``float``: times (s), rates (Hz), counts, angles (rad), ratios, scores and pixel
quantities of an image (they belong to the camera and its detector, not to the size of the site).

Times are not scaled: sensors run at 10 Hz at every size. The characteristic length of a scene is its
vehicle's length; its characteristic speed the highest lane speed limit, or ``design_speed_mps``
for a site without a lane map; its characteristic acceleration the vehicle's ``max_accel_mps2``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any, TypeVar

from pydantic import BaseModel

if TYPE_CHECKING:
    from shared.scene.model import SceneSpec

#: The reference site every scaled default was tuned on: the sand table's vehicle length and
#: acceleration (an AWS DeepRacer, deploy/scenes/sand_table.yaml) and its lanes' top speed limit. A
#: test checks that the sand table's scale is exactly 1.
REFERENCE_LENGTH_M = 0.33
REFERENCE_SPEED_MPS = 0.5
REFERENCE_ACCEL_MPS2 = 0.6


@dataclass(frozen=True)
class Scales:
    """Marker in a field's `Annotated` type: how its default scales. `power_length`, `power_speed` and
    `power_accel` are the exponents of L, V and A in its factor."""

    kind: str
    power_length: int = 0
    power_speed: int = 0
    power_accel: int = 0


@dataclass(frozen=True)
class FromSceneMarker:
    """Marker of a setting the builder reads from the scene (`what` says where from)."""

    what: str


LENGTH = Scales("length", power_length=1)
AREA = Scales("area", power_length=2)
PER_LENGTH = Scales("per_length", power_length=-1)
SPEED = Scales("speed", power_speed=1)
ACCELERATION = Scales("acceleration", power_accel=1)
RATIO = Scales("ratio")

Length = Annotated[float, LENGTH]
Area = Annotated[float, AREA]
PerLength = Annotated[float, PER_LENGTH]
Speed = Annotated[float, SPEED]
Acceleration = Annotated[float, ACCELERATION]
Ratio = Annotated[float, RATIO]
Length3 = Annotated[tuple[float, float, float], LENGTH]


def from_scene(what: str) -> FromSceneMarker:
    """`Annotated[T, from_scene("the agent's lidars' max_range_m")]`: set by the builder from the scene."""
    return FromSceneMarker(what)


@dataclass(frozen=True)
class SiteScale:
    """The factors of one scene against the reference site (1, 1, 1 on the sand table)."""

    length: float
    speed: float
    accel: float

    def __post_init__(self) -> None:
        factors = (self.length, self.speed, self.accel)
        if not all(f > 0 and math.isfinite(f) for f in factors):
            raise ValueError(f"scale factors must be positive and finite, got {factors}")

    @classmethod
    def of(cls, spec: SceneSpec) -> SiteScale:
        """The scale of a scene: its vehicle's length and acceleration and its top speed against the
        reference's."""
        return cls(
            spec.vehicle.length_m / REFERENCE_LENGTH_M,
            spec.top_speed_mps / REFERENCE_SPEED_MPS,
            spec.vehicle.max_accel_mps2 / REFERENCE_ACCEL_MPS2,
        )

    def factor(self, scales: Scales) -> float:
        """The factor of a kind at this scale (1 for a ratio)."""
        return float(
            self.length**scales.power_length * self.speed**scales.power_speed * self.accel**scales.power_accel
        )


REFERENCE = SiteScale(1.0, 1.0, 1.0)


def scales_of(field_metadata: list[Any]) -> Scales | FromSceneMarker | None:
    """The scaling marker among a pydantic field's metadata, if any."""
    for item in field_metadata:
        if isinstance(item, Scales | FromSceneMarker):
            return item
    return None


def _scaled_value(value: Any, factor: float) -> Any:
    if value is None:
        return None
    if isinstance(value, tuple):
        return tuple(_scaled_value(v, factor) for v in value)
    return float(value) * factor


M = TypeVar("M", bound=BaseModel)


def at_scale(model: M, scale: SiteScale, *, defaulted: bool = False) -> M:
    """`model` with every scaled setting left at its default multiplied by its kind's factor, nested
    models included (a nested model that is itself a default, from its field's default or default
    factory, counts as default throughout: `defaulted`). Settings given explicitly stay as written.
    The result has every scaled setting marked as given, so building it again for the same scale
    changes nothing (idempotent)."""
    update: dict[str, Any] = {}
    for name, info in type(model).model_fields.items():
        value = getattr(model, name)
        unset = defaulted or name not in model.model_fields_set
        if isinstance(value, BaseModel):
            scaled = at_scale(value, scale, defaulted=unset)
            if scaled is not value:
                update[name] = scaled
            continue
        marker = scales_of(info.metadata)
        if isinstance(marker, Scales) and unset:
            update[name] = _scaled_value(value, scale.factor(marker))
    return model.model_copy(update=update) if update else model


def scaled_fields(model: BaseModel, prefix: str = "") -> dict[str, tuple[Scales | FromSceneMarker, Any]]:
    """Every scaled or scene-read setting of `model` and its nested models: dotted path -> (marker,
    value). What the any-scale test compares between a table core and a 1:1 core."""
    out: dict[str, tuple[Scales | FromSceneMarker, Any]] = {}
    for name, info in type(model).model_fields.items():
        value = getattr(model, name)
        path = f"{prefix}{name}"
        if isinstance(value, BaseModel):
            out.update(scaled_fields(value, f"{path}."))
            continue
        marker = scales_of(info.metadata)
        if marker is not None:
            out[path] = (marker, value)
    return out

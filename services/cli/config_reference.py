"""The configuration reference (docs/configuration.md), generated from the pydantic models that read
every YAML file of the project.

    .venv/bin/python -m services.cli.config_reference > docs/configuration.md

One section per kind of file (`FILES`: the model, where such files live), one table per model: each
field's YAML name, type, default, bounds and description, nested models as tables of their own (each
once, linked from where it is used). Units are in the names (`_m`, `_s`, `_hz`, ...) and the
descriptions. A test fails when docs/configuration.md is out of date.
"""

from __future__ import annotations

import enum
import re
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from annotated_types import Ge, Gt, Le, Lt, MaxLen, MinLen
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from shared.paths import REPO_ROOT

HEADER = """# Configuration reference

Every YAML file the project reads, field by field, as its pydantic model checks it: a file with an
unknown field, a wrong type or a value out of bounds is refused with one line naming the field. This page
is generated from the models by `.venv/bin/python -m services.cli.config_reference >
docs/configuration.md`; a test fails when it is out of date. Units are in the names (`_m` metres, `_s`
seconds, `_hz` hertz, `_mps` metres per second, `_rad` radians, `_px` pixels) and the descriptions;
settings files are also overridden by environment variables (`RMMDET_<SERVICE>_<FIELD>`, nested with
`__`, e.g. `RMMDET_MEC_SYNC__MAX_WAIT_S=0.3`).
"""


@dataclass(frozen=True)
class FileKind:
    title: str
    model: str  # module:attribute of the model (imported on use)
    where: str  # where such files live


FILES = (
    FileKind("Scene", "shared.scene.model:SceneSpec", "`deploy/scenes/*.yaml`"),
    FileKind("Site devices", "shared.devices.site:SiteFile", "`deploy/devices/*.yaml`"),
    FileKind("Camera model card", "shared.detection.card:CameraCard", "`card:` in `deploy/models/**/*.yaml`"),
    FileKind("Lidar model card", "shared.detection.card:LidarCard", "`card:` in `deploy/models/**/*.yaml`"),
    FileKind(
        "Capture mapping", "shared.captures.mapping:Mapping", "`--mapping` of `rmmdet import` / `replay`"
    ),
    FileKind("Multi-host layout", "shared.security.sites:Layout", "`deploy/sites/*.yaml`"),
    FileKind("Launch profile", "shared.supervision.profiles:Profile", "`deploy/profiles/**/*.yaml`"),
    FileKind("MEC settings", "shared.perception.config:MecSettings", "`deploy/mec/mec.yaml`"),
    FileKind(
        "Coordinator settings",
        "shared.traffic.config:CoordinatorSettings",
        "`deploy/coordinator/coordinator.yaml`",
    ),
    FileKind("Simulator settings", "sim.config:SimSettings", "`deploy/sim/sim.yaml`"),
    FileKind(
        "Vehicle client settings",
        "shared.vehicle.config:VehicleSettings",
        "environment only (`rmmdet vehicle`)",
    ),
    FileKind("Dataset", "studies.dataset.config:DatasetSettings", "`deploy/datasets/*.yaml`"),
    FileKind(
        "Flow experiment",
        "studies.experiments.config:FlowExperimentSettings",
        "`deploy/experiments/flow.yaml`",
    ),
    FileKind("City study", "studies.city.config:CityStudySettings", "`deploy/experiments/city.yaml`"),
    FileKind(
        "Real-city study", "studies.city.real:RealCitiesSettings", "`deploy/experiments/city-real.yaml`"
    ),
)


def load(kind: FileKind) -> type[BaseModel]:
    import importlib

    module, name = kind.model.split(":")
    model = getattr(importlib.import_module(module), name)
    assert isinstance(model, type) and issubclass(model, BaseModel), kind.model
    return model


def _anchor(model: type[BaseModel]) -> str:
    return model.__name__.lower()


def _type(annotation: Any, nested: list[type[BaseModel]]) -> str:
    """A readable type; models met are added to `nested` (and linked)."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Annotated:
        return _type(args[0], nested)
    if origin in (typing.Union, types.UnionType):
        parts = [_type(a, nested) for a in args if a is not type(None)]
        return " or ".join(parts) + (" or null" if type(None) in args else "")
    if origin is typing.Literal:
        return " / ".join(f"`{a}`" for a in args)
    if origin in (list, tuple, set, frozenset):
        inner = ", ".join(_type(a, nested) for a in args if a is not Ellipsis)
        return f"list of {inner}" if origin is not tuple or Ellipsis in args else f"({inner})"
    if origin is dict:
        return f"map {_type(args[0], nested)} → {_type(args[1], nested)}"
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        if annotation not in nested:
            nested.append(annotation)
        return f"[{annotation.__name__}](#{_anchor(annotation)})"
    if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
        return " / ".join(f"`{m.value}`" for m in annotation)
    if isinstance(annotation, type):
        return {"str": "text", "int": "integer", "float": "number", "bool": "true/false", "Path": "path"}.get(
            annotation.__name__, annotation.__name__
        )
    return re.sub(r"typing\.|[a-z_]+\.", "", str(annotation))


def _bounds(field: FieldInfo) -> str:
    out = []
    for m in field.metadata:
        for cls, attr, sign in ((Ge, "ge", "≥"), (Gt, "gt", ">"), (Le, "le", "≤"), (Lt, "lt", "<")):
            if isinstance(m, cls):
                out.append(f"{sign} {getattr(m, attr)}")
        if isinstance(m, MinLen):
            out.append(f"at least {m.min_length} items")
        if isinstance(m, MaxLen):
            out.append(f"at most {m.max_length} items")
        pattern = getattr(m, "pattern", None)
        if pattern:
            out.append(f"matches `{pattern}`")
    return ", ".join(out)


def _default(field: FieldInfo) -> str:
    if field.default_factory is not None:
        try:
            value = field.default_factory()  # type: ignore[call-arg]
        except TypeError:
            return "(computed)"
    elif field.default is PydanticUndefined:
        return "**required**"
    else:
        value = field.default
    if isinstance(value, BaseModel):
        return "(its defaults)"
    if isinstance(value, enum.Enum):
        value = value.value
    text = str(value).replace(f"{REPO_ROOT}/", "")
    if isinstance(value, Path):
        text = (
            str(value.relative_to(REPO_ROOT))
            if value.is_absolute() and value.is_relative_to(REPO_ROOT)
            else text
        )
    text = text if len(text) <= 60 else text[:57] + "..."
    return f"`{text}`"


def _cell(text: str | None) -> str:
    return " ".join((text or "").split()).replace("|", "\\|")


def model_table(model: type[BaseModel], nested: list[type[BaseModel]]) -> list[str]:
    lines = ["| field | type | default | bounds | description |", "|---|---|---|---|---|"]
    for name, field in model.model_fields.items():
        key = field.alias or name
        lines.append(
            f"| `{key}` | {_cell(_type(field.annotation, nested))} | {_cell(_default(field))} | "
            f"{_cell(_bounds(field))} | {_cell(field.description)} |"
        )
    return lines


def reference() -> str:
    out = [HEADER]
    done: set[type[BaseModel]] = set()
    for kind in FILES:
        root = load(kind)
        out += [
            f"## {kind.title}",
            "",
            f"Model `{root.__module__}.{root.__name__}`; files: {kind.where}.",
            "",
        ]
        doc = (root.__doc__ or "").strip()
        if doc and not doc.startswith("Usage docs"):
            out += [_cell(doc), ""]
        queue: list[type[BaseModel]] = [root]
        while queue:
            model = queue.pop(0)
            if model in done:
                continue
            done.add(model)
            nested: list[type[BaseModel]] = []
            if model is not root:
                out += [f"### {model.__name__}", ""]  # its anchor: toc's slug of the name, `_anchor`
            elif _anchor(root) != re.sub(r"[^a-z0-9-]", "", kind.title.lower().replace(" ", "-")):
                out += [f'<a id="{_anchor(root)}"></a>', ""]
            out += model_table(model, nested)
            out.append("")
            queue += [m for m in nested if m not in done]
    return "\n".join(out).rstrip() + "\n"


if __name__ == "__main__":
    print(reference(), end="")

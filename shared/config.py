"""Typed service settings: a YAML file, overridden by environment variables, validated by pydantic.

    class MecSettings(RmmdetSettings):
        model_config = settings_config(env_prefix="RMMDET_MEC_")
        iou_threshold: float = Field(0.7, ge=0, le=1, description="Algorithm 2 match threshold")

    settings = load_settings(MecSettings, Path("deploy/local/mec.yaml"))

Priority: environment (`RMMDET_MEC_IOU_THRESHOLD=0.6`, nested with `__`) > YAML file > defaults.
Every parameter carries a type, a default and a description, so `model_json_schema()` documents it.
Unknown keys are errors (a typo must not silently fall back to a default).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

ENV_PREFIX = "RMMDET_"


def settings_config(env_prefix: str = ENV_PREFIX, **kwargs: Any) -> SettingsConfigDict:
    return SettingsConfigDict(env_prefix=env_prefix, env_nested_delimiter="__", extra="forbid", **kwargs)  # type: ignore[typeddict-item]


class RmmdetSettings(BaseSettings):
    model_config = settings_config()

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # init kwargs carry the YAML file's content: environment variables win over it.
        return (env_settings, init_settings)


class ConfigError(ValueError):
    """A settings file or environment override that does not validate."""


S = TypeVar("S", bound=BaseSettings)
M = TypeVar("M", bound=BaseModel)


def read_yaml(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: invalid YAML: {err}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping, got {type(data).__name__}")
    return data


def deep_merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """`base` with `override` merged in, section by section: a nested mapping in `override` updates the
    same section of `base` key by key instead of replacing it (`{"detectors": {"camera": "oracle"}}`
    changes the camera detector and keeps the section's other settings). Neither input is modified."""
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def with_overrides(model: M, overrides: Mapping[str, Any]) -> M:
    """A copy of `model` with `overrides` deep-merged in (`deep_merge`) and validated like a file:
    `with_overrides(mec, {"detectors": {"camera_threads": 1}})`. The one way settings are overridden
    in code; environment variables are not read again. What was left at its default stays so (only the
    given values and the overrides are validated), so a size default still scales with the scene it is
    built for (shared/scene/scale.py)."""
    try:
        return type(model).model_validate(deep_merge(model.model_dump(exclude_unset=True), dict(overrides)))
    except ValidationError as err:
        raise ConfigError(f"{type(model).__name__}: {err}") from None


def validation_summary(err: ValidationError) -> str:
    """A pydantic error as one line: each wrong field's dotted path and what is wrong with it."""
    return "; ".join(
        f"{'.'.join(str(p) for p in e['loc']) or '(top level)'}: {e['msg']}" for e in err.errors()
    )


def load_settings(cls: type[S], yaml_path: Path | None = None, **overrides: Any) -> S:
    """Settings of type `cls` from `yaml_path` (optional) with keyword overrides deep-merged in
    (`deep_merge`), then env vars."""
    data = deep_merge(read_yaml(yaml_path) if yaml_path is not None else {}, overrides)
    try:
        return cls(**data)
    except ValidationError as err:
        where = f"{yaml_path}" if yaml_path else cls.__name__
        raise ConfigError(f"{where}: {validation_summary(err)}") from None

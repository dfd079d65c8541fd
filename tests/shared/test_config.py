"""Settings: YAML file, environment overrides, strict validation with the file named."""

from __future__ import annotations

import pytest
from pydantic import BaseModel, Field

from shared.config import (
    ConfigError,
    RmmdetSettings,
    deep_merge,
    load_settings,
    settings_config,
    with_overrides,
)
from shared.perception.config import DEFAULT_MEC_CONFIG, MecSettings
from shared.traffic.config import CoordinatorSettings
from sim.config import SimSettings
from studies.dataset.config import DatasetSettings
from studies.experiments.config import FlowExperimentSettings


class _Kalman(BaseModel):
    process_noise: float = Field(0.1, gt=0, description="q")


class _DemoSettings(RmmdetSettings):
    model_config = settings_config(env_prefix="RMMDET_DEMO_")
    iou_threshold: float = Field(0.7, ge=0, le=1, description="match threshold")
    agent: str = Field("agent1", description="agent id")
    kalman: _Kalman = Field(default_factory=_Kalman)


def test_defaults_yaml_and_env_priority(tmp_path, monkeypatch) -> None:
    assert load_settings(_DemoSettings).iou_threshold == 0.7
    f = tmp_path / "demo.yaml"
    f.write_text("iou_threshold: 0.6\nkalman: {process_noise: 0.5}\n")
    assert load_settings(_DemoSettings, f).iou_threshold == 0.6
    monkeypatch.setenv("RMMDET_DEMO_IOU_THRESHOLD", "0.55")
    monkeypatch.setenv("RMMDET_DEMO_KALMAN__PROCESS_NOISE", "0.25")
    s = load_settings(_DemoSettings, f)
    assert (s.iou_threshold, s.kalman.process_noise, s.agent) == (0.55, 0.25, "agent1")


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("iou_threshold: 1.5\n", "less than or equal"),
        ("iou_treshold: 0.5\n", "Extra inputs"),  # typo must not silently fall back to a default
        ("- a\n- b\n", "top level must be a mapping"),
        ("iou_threshold: [\n", "invalid YAML"),
    ],
)
def test_invalid_settings_name_the_file(tmp_path, text: str, match: str) -> None:
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=match) as info:
        load_settings(_DemoSettings, f)
    assert "bad.yaml" in str(info.value)


def test_empty_file_gives_defaults(tmp_path) -> None:
    f = tmp_path / "empty.yaml"
    f.write_text("")
    assert load_settings(_DemoSettings, f).agent == "agent1"


def undocumented(model: type[BaseModel], prefix: str = "") -> list[str]:
    """Fields of `model` and of its nested sections without a description."""
    out = []
    for name, info in model.model_fields.items():
        nested = info.annotation if isinstance(info.annotation, type) else None
        if nested is not None and issubclass(nested, BaseModel):
            out += undocumented(nested, f"{prefix}{name}.")
        elif not info.description:
            out.append(prefix + name)
    return out


@pytest.mark.parametrize(
    "cls",
    [MecSettings, CoordinatorSettings, SimSettings, FlowExperimentSettings, DatasetSettings],
    ids=lambda c: c.__name__,
)
def test_every_service_parameter_is_documented(cls: type[BaseModel]) -> None:
    """The settings files point to the classes for what each field means: every one must say."""
    assert undocumented(cls) == []


def test_the_documentation_check_finds_a_missing_description() -> None:
    class Inner(BaseModel):
        a: float = Field(1.0, description="documented")
        b: float = 2.0

    class Outer(BaseModel):
        inner: Inner = Field(default_factory=Inner)
        c: int = 0

    assert undocumented(Outer) == ["inner.b", "c"]


def test_overrides_merge_into_nested_sections(tmp_path) -> None:
    """An override of one field of a section keeps the section's other fields (file and code alike)."""
    f = tmp_path / "demo.yaml"
    f.write_text("agent: agent2\nkalman: {process_noise: 0.5}\n")
    s = load_settings(_DemoSettings, f, kalman={})
    assert (s.agent, s.kalman.process_noise) == ("agent2", 0.5)
    mec = load_settings(MecSettings, DEFAULT_MEC_CONFIG, detectors={"camera": "oracle"})
    assert mec.detectors.camera == "oracle" and mec.detectors.camera_precision == "int8"  # from the file
    changed = with_overrides(mec, {"detectors": {"lidar_threads": 2}, "sync": {"max_wait_s": 0.3}})
    assert (changed.detectors.lidar_threads, changed.detectors.camera, changed.sync.max_wait_s) == (
        2,
        "oracle",
        0.3,
    )
    assert changed.health == mec.health and mec.sync.max_wait_s != 0.3  # the original is untouched
    with pytest.raises(ConfigError, match="max_wait_s"):
        with_overrides(mec, {"sync": {"max_wait_s": -1}})


def test_deep_merge_replaces_leaves_and_merges_mappings() -> None:
    base = {"a": {"x": 1, "y": {"p": 1}}, "b": 2}
    assert deep_merge(base, {"a": {"y": {"q": 2}}, "b": {"new": 1}}) == {
        "a": {"x": 1, "y": {"p": 1, "q": 2}},
        "b": {"new": 1},
    }
    assert base == {"a": {"x": 1, "y": {"p": 1}}, "b": 2}

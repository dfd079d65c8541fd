"""Settings: YAML file, environment overrides, strict validation with the file named."""

from __future__ import annotations

import pytest
from pydantic import BaseModel, Field

from shared.config import ConfigError, RmmdetSettings, load_settings, settings_config


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


def test_json_schema_documents_every_parameter() -> None:
    schema = _DemoSettings.model_json_schema()
    for name in ("iou_threshold", "agent"):
        assert schema["properties"][name]["description"]

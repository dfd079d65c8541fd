"""Key selection for record/replay and the default output path."""

from __future__ import annotations

import time
from pathlib import Path

from shared.recording.bus import key_filter, overlapping
from shared.recording.writer import default_recording_path
from tests.shared.recording.samples import CAMERA_KEY, GROUND_TRUTH_KEY, RADAR_KEY


def test_key_filter_uses_zenoh_key_expression_semantics() -> None:
    assert key_filter([]) is None
    agent1 = key_filter(["rmmdet/v1/agent1/**"])
    assert agent1 is not None
    assert agent1(CAMERA_KEY) and agent1(RADAR_KEY) and not agent1(GROUND_TRUTH_KEY)
    cameras = key_filter(["rmmdet/v1/*/sensor/camera/*", GROUND_TRUTH_KEY])
    assert cameras is not None
    assert cameras(CAMERA_KEY) and cameras(GROUND_TRUTH_KEY) and not cameras(RADAR_KEY)
    data = key_filter(["rmmdet/v1/**"])
    assert data is not None
    assert not data("rmmdet/v1/agent1/@health/mec/agent1")  # verbatim chunks stay out of wildcards


def test_overlapping_patterns_are_reported() -> None:
    assert overlapping(["rmmdet/v1/**", "rmmdet/v1/agent1/**"]) == [("rmmdet/v1/**", "rmmdet/v1/agent1/**")]
    assert overlapping(["rmmdet/v1/agent1/**", "rmmdet/v1/agent2/**"]) == []


def test_default_recording_path_is_timestamped() -> None:
    now_s = time.mktime((2026, 3, 4, 5, 6, 7, 0, 0, -1))
    assert default_recording_path(now_s, Path("/rec")) == Path("/rec/rmmdet-20260304-050607.mcap")

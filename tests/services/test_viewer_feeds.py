"""The viewer's sensor feeds: a sensor's bus subscription exists exactly while some client watches its
channel (two clients on one channel: one subscription, gone when the last leaves)."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from rmmdet.v1.common_pb2 import Header
from rmmdet.v1.health_pb2 import HEALTH_LEVEL_NOMINAL, ServiceHealth
from rmmdet.v1.sensors_pb2 import RadarScan

from shared.bus.codec import Counters, encode, encoding_for
from shared.paths import DEFAULT_SCENE, REPO_ROOT
from shared.perception.output import detections_2d_message
from shared.scene.scene import Scene
from shared.supervision.verdict import Verdict
from shared.viewer.core import FRAMES, GRID, GROUND_TRUTH, PLANS, TABLE, tracks_topic
from shared.viewer.feeds import Outlets, SensorFeeds
from shared.viewer.foxglove_ws import ViewHub
from shared.viewer.health_feed import HEALTH_SCHEMA, HealthFeed, health_json


@dataclass
class FakeSub:
    key: str
    callback: Callable[[Any], None]
    undeclared: bool = False

    def undeclare(self) -> None:
        self.undeclared = True


@dataclass
class FakeSession:
    subs: list[FakeSub] = field(default_factory=list)

    def declare_subscriber(self, key: str, callback: Callable[[Any], None]) -> FakeSub:
        self.subs.append(FakeSub(key, callback))
        return self.subs[-1]


@dataclass(frozen=True)
class Bytes:
    data: bytes

    def to_bytes(self) -> bytes:
        return self.data


@dataclass(frozen=True)
class FakeSample:
    payload: Bytes
    encoding: str
    attachment: Bytes | None


def test_a_sensor_is_subscribed_only_while_watched(test_scene: Scene) -> None:
    feeds = SensorFeeds(test_scene, Outlets(ViewHub()))
    spec = next(s for s in test_scene.spec.sensors if s.kind == "camera")
    topic = f"/agents/{spec.agent}/camera/{spec.id}"
    feeds.on_subscribe(topic)  # before the bus is there: made on attach
    session = FakeSession()
    feeds.attach(session, Counters())  # type: ignore[arg-type]
    assert [s.key for s in session.subs] == [f"rmmdet/v1/{spec.agent}/sensor/camera/{spec.id}"]
    feeds.on_subscribe(topic)  # a second client: no second subscription
    assert len(session.subs) == 1 and feeds.subscribed == [topic]
    feeds.on_unsubscribe(topic)
    assert not session.subs[0].undeclared
    feeds.on_unsubscribe(topic)
    assert session.subs[0].undeclared and feeds.subscribed == []
    feeds.on_unsubscribe(topic)  # an extra unsubscribe changes nothing
    feeds.on_subscribe("/table")  # not a sensor channel: not the feeds' business
    assert len(session.subs) == 1


def test_the_layout_names_only_topics_the_viewer_serves() -> None:
    """deploy/foxglove/rmmdet-layout.json (open it in Foxglove or Lichtblick) refers to real channels of
    the default scene."""
    scene = Scene.load(DEFAULT_SCENE)
    layout = json.loads((REPO_ROOT / "deploy" / "foxglove" / "rmmdet-layout.json").read_text())
    text = json.dumps(layout["configById"])
    named = set(re.findall(r'"(/[a-z0-9_/]+)"', text))
    served = {TABLE, FRAMES, GROUND_TRUTH, PLANS, GRID, HealthFeed.TOPIC}
    served |= {tracks_topic(a) for a in scene.agents} | set(SensorFeeds(scene, Outlets(ViewHub())).topics)
    assert named and named <= served, named - served


def test_detections_are_drawn_as_annotations_while_watched(test_scene: Scene) -> None:
    """Watching a camera's `/detections` channel subscribes to the MEC's 2D detections of that camera
    (which makes the MEC publish them); each one becomes an ImageAnnotations, bad ones are counted."""
    feeds = SensorFeeds(test_scene, Outlets(ViewHub()))
    spec = next(s for s in test_scene.spec.sensors if s.kind == "camera")
    topic = f"/agents/{spec.agent}/camera/{spec.id}/detections"
    session, counters = FakeSession(), Counters()
    feeds.attach(session, counters)  # type: ignore[arg-type]
    feeds.on_subscribe(topic)
    (sub,) = session.subs
    assert sub.key == f"rmmdet/v1/{spec.agent}/perception/detections_2d/{spec.id}"
    msg = detections_2d_message(spec.id, np.array([[10, 20, 50, 40, 0.75, 0]], np.float32), 448, 336)
    header = Header(source_id="agent/mec", seq=1)
    header.stamp.FromNanoseconds(1_000_000_000)
    encoded = encode(msg, header)
    sub.callback(FakeSample(Bytes(encoded.payload), str(encoding_for(msg)), Bytes(encoded.attachment)))
    sub.callback(FakeSample(Bytes(b"\xff\xff"), str(encoding_for(msg)), None))
    snapshot = counters.snapshot()
    assert snapshot["drawn/Detection2DArray"] == 1
    assert snapshot["rejected/decode"] == 1
    feeds.on_unsubscribe(topic)
    assert sub.undeclared


def test_radar_scans_are_drawn_as_targets_while_watched(test_scene: Scene) -> None:
    feeds = SensorFeeds(test_scene, Outlets(ViewHub()))
    spec = next(s for s in test_scene.spec.sensors if s.kind == "radar")
    session, counters = FakeSession(), Counters()
    feeds.attach(session, counters)  # type: ignore[arg-type]
    feeds.on_subscribe(f"/agents/{spec.agent}/radar/{spec.id}/targets")
    (sub,) = session.subs
    assert sub.key == f"rmmdet/v1/{spec.agent}/sensor/radar/{spec.id}"  # the scans themselves
    scan = RadarScan(sensor_id=spec.id)
    scan.targets.add(range_m=1.0, azimuth_rad=0.1, range_rate_mps=-0.3)
    scan.header.stamp.FromNanoseconds(1_000_000_000)
    encoded = encode(scan)
    sub.callback(FakeSample(Bytes(encoded.payload), str(encoding_for(scan)), None))
    assert counters.snapshot()["drawn/RadarScan"] == 1


def test_the_health_schema_describes_what_health_carries() -> None:
    """`/health`'s JSON Schema (viewers read it) names exactly the fields health_json writes."""
    report = ServiceHealth(service="mec", instance="agent1", level=HEALTH_LEVEL_NOMINAL, message="full")
    sample = health_json(Verdict(reports=[report]))
    schema = json.loads(HEALTH_SCHEMA.data)
    assert set(schema["properties"]) == set(sample)
    assert set(schema["properties"]["services"]["items"]["properties"]) == set(sample["services"][0])

"""The viewer's Foxglove channels and its sensor feeds (services/viewer is the process around them).

An `Outlet` is one channel, to the viewer's WebSocket clients that subscribe (shared/viewer/
foxglove_ws.py) and into an MCAP recording; `Channels` makes one per drawn topic on first use and says
whether anyone watches it (draw only then); `SensorFeeds` forwards camera images, lidar clouds and radar
scans from the bus untouched and draws each camera's 2D detections and each radar's targets,
subscribing on the bus only while some client watches the channel.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import foxglove
import zenoh
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf.message import Message
from rmmdet.v1 import perception_pb2 as pb
from rmmdet.v1.sensors_pb2 import RadarScan

from shared.bus.codec import Counters, MessageDecoder
from shared.bus.streams import SENSOR_STREAM, get_stream
from shared.scene.scene import Scene
from shared.viewer.foxglove_ws import ViewHub, ViewSchema, protobuf_schema
from shared.viewer.scene import image_annotations, radar_targets


class Outlet:
    """One channel of the view: to the clients of the viewer's server (ViewHub) that subscribe to it,
    and into the MCAP recording when one is open on the context (foxglove-sdk writes it)."""

    def __init__(self, hub: ViewHub, context: foxglove.Context, topic: str, schema: ViewSchema) -> None:
        self.topic = topic
        self._hub = hub
        hub.channel(topic, schema)
        self._recorded = foxglove.Channel(
            topic,
            schema=foxglove.Schema(name=schema.name, encoding=schema.encoding, data=schema.data),
            message_encoding=schema.message_encoding,
            context=context,
        )

    def has_sinks(self) -> bool:
        """True if a client watches the channel or it is being recorded (draw only then)."""
        return self._hub.watched(self.topic) or self._recorded.has_sinks()

    def log(self, payload: bytes, log_time_ns: int) -> None:
        self._hub.log(self.topic, payload, log_time_ns)
        if self._recorded.has_sinks():
            self._recorded.log(payload, log_time=log_time_ns)


@dataclass(frozen=True)
class Outlets:
    """Where the viewer's channels go: its WebSocket clients (`hub`) and the MCAP sink of `context`."""

    hub: ViewHub
    context: foxglove.Context = field(default_factory=foxglove.Context)

    def open(self, topic: str, schema: ViewSchema) -> Outlet:
        return Outlet(self.hub, self.context, topic, schema)


class Channels:
    """The viewer's drawn channels, made on first use (one per topic)."""

    def __init__(self, outlets: Outlets) -> None:
        self._outlets = outlets
        self._channels: dict[str, Outlet] = {}

    def wants(self, topic: str, message_type: type[Message]) -> bool:
        """True if some client subscribes to `topic` (advertised from the first call on): draw only then."""
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._outlets.open(topic, protobuf_schema(message_type))
            self._channels[topic] = channel
        return channel.has_sinks()

    def log(self, topic: str, msg: Message, stamp_ns: int) -> None:
        self._channels[topic].log(msg.SerializeToString(), stamp_ns)


class SensorFeeds:
    """Camera images, lidar clouds and radar scans from the bus to the view, untouched (their payloads
    are Foxglove / rmmdet protobufs already), each camera's 2D detections as image annotations
    (`<camera topic>/detections`) and each radar's targets as spheres (`<radar topic>/targets`): a bus
    subscription exists only while some client subscribes to its channel, so an idle viewer costs
    nothing for them (and the MEC publishes no detections). The hub's SubscriptionListener (its
    callbacks run on the clients' threads; the bus callbacks on Zenoh's)."""

    def __init__(self, scene: Scene, outlets: Outlets) -> None:
        self._counters: Counters | None = None
        self._session: zenoh.Session | None = None
        self._lock = threading.Lock()
        self._keys: dict[str, str] = {}  # topic -> bus key
        self._channels: dict[str, Outlet] = {}
        self._watchers: Counter[str] = Counter()
        self._subscribers: dict[str, Any] = {}
        # Topics drawn from a bus message rather than forwarded: its type and the drawing.
        self._convert: dict[str, tuple[type[Message], Callable[[Any, int], Message]]] = {}
        for spec in scene.spec.sensors:
            stream = get_stream(SENSOR_STREAM[spec.kind])
            topic = f"/agents/{spec.agent}/{spec.kind}/{spec.id}"
            self._add(outlets, topic, stream.key(agent=spec.agent, sensor=spec.id), stream.message_type)
            if spec.kind == "camera":
                key = get_stream("detections_2d").key(agent=spec.agent, sensor=spec.id)
                self._add(outlets, f"{topic}/detections", key, ImageAnnotations)
                self._convert[f"{topic}/detections"] = (pb.Detection2DArray, image_annotations)
            elif spec.kind == "radar":
                self._add(outlets, f"{topic}/targets", self._keys[topic], SceneUpdate)
                self._convert[f"{topic}/targets"] = (RadarScan, radar_targets)

    def _add(self, outlets: Outlets, topic: str, key: str, message_type: type[Message]) -> None:
        self._keys[topic] = key
        self._channels[topic] = outlets.open(topic, protobuf_schema(message_type))

    def attach(self, session: zenoh.Session, counters: Counters) -> None:
        """The bus to subscribe on and the counters to count on (subscriptions asked for before are
        made now)."""
        with self._lock:
            self._session, self._counters = session, counters
            for topic, n in self._watchers.items():
                if n > 0 and topic not in self._subscribers:
                    self._subscribe(topic)

    def _subscribe(self, topic: str) -> None:
        assert self._session is not None and self._counters is not None
        channel, counters = self._channels[topic], self._counters
        if topic in self._convert:
            # Drawn from the bus message (2D detections: subscribing is what makes the MEC publish
            # them at all; radar targets: from the radar's own scans).
            message_type, drawing = self._convert[topic]
            decoder = MessageDecoder(message_type, counters)
            name = message_type.DESCRIPTOR.name

            def convert(sample: zenoh.Sample) -> None:
                attachment = sample.attachment.to_bytes() if sample.attachment is not None else None
                decoded = decoder.decode(sample.payload.to_bytes(), str(sample.encoding), attachment)
                if decoded is not None:
                    drawn = drawing(decoded.message, decoded.header.stamp.ToNanoseconds())
                    channel.log(drawn.SerializeToString(), time.time_ns())
                    counters.inc(f"drawn/{name}")

            self._subscribers[topic] = self._session.declare_subscriber(self._keys[topic], convert)
            return

        def forward(sample: zenoh.Sample) -> None:
            channel.log(sample.payload.to_bytes(), time.time_ns())
            counters.inc("forwarded/sensor")

        self._subscribers[topic] = self._session.declare_subscriber(self._keys[topic], forward)

    def on_subscribe(self, topic: str) -> None:
        with self._lock:
            if topic not in self._keys:
                return
            self._watchers[topic] += 1
            if self._session is not None and topic not in self._subscribers:
                self._subscribe(topic)

    def on_unsubscribe(self, topic: str) -> None:
        with self._lock:
            if topic not in self._keys or self._watchers[topic] == 0:
                return
            self._watchers[topic] -= 1
            if self._watchers[topic] == 0 and (sub := self._subscribers.pop(topic, None)):
                sub.undeclare()

    @property
    def topics(self) -> list[str]:
        """Every channel the feeds serve (sensor feeds and what is drawn from them)."""
        return sorted(self._channels)

    @property
    def subscribed(self) -> list[str]:
        """The topics subscribed on the bus right now."""
        with self._lock:
            return sorted(self._subscribers)

    def close(self) -> None:
        with self._lock:
            for sub in self._subscribers.values():
                sub.undeclare()
            self._subscribers.clear()
